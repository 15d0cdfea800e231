"""Tracking evaluation: metrics, the evaluation harness, plots."""
