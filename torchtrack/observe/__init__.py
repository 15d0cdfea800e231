"""Observation models: likelihoods over particle states (calibrated detector, adaptive Haar, Haar box features read from an integral image, co-trained pixels, template, colour histogram)."""
