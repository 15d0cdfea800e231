"""Trackers: one interface (init / update -> TrackState) over filters and observation models."""
