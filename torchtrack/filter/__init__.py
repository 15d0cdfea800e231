"""Batched particle filters: particle sets, resampling, motion models, SIR, SEIR."""
