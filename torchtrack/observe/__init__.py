"""Observation models: likelihoods over particle states (calibrated detector, adaptive Haar, co-trained pixels, template, colour histogram)."""
