"""Integral images and feature banks (Haar wavelets, centre-surround, pixel colour / texture)."""
