"""Batched particle filters: particle sets, resampling, motion models, SIR, SEIR.

Shapes: particles ``(B, N, D)``, log-weights ``(B, N)``; dtype and device follow the input;
randomness only from an explicit ``generator`` (one ``torch.Generator`` or one per batch row).
"""

from torchtrack.filter.dynamics_fit import (
    ChateauFit,
    fit_chateau_dynamics,
    load_chateau_toml,
    save_chateau_toml,
)
from torchtrack.filter.graph import GraphedSIR
from torchtrack.filter.motion import BachooMotion, ChateauAR, KleinAR, VelocityHistory
from torchtrack.filter.particles import (
    ParticleSet,
    best_particle,
    dominant_mode_mean,
    ess,
    normalize_log_weights,
    uniform_log_weights,
    weighted_cov,
    weighted_mean,
)
from torchtrack.filter.resample import RESAMPLERS, get_resampler, resample
from torchtrack.filter.seir import seir_step
from torchtrack.filter.sir import ESTIMATORS, StepResult, sir_step

__all__ = [
    "ESTIMATORS",
    "RESAMPLERS",
    "BachooMotion",
    "ChateauAR",
    "ChateauFit",
    "GraphedSIR",
    "KleinAR",
    "ParticleSet",
    "StepResult",
    "VelocityHistory",
    "best_particle",
    "dominant_mode_mean",
    "ess",
    "fit_chateau_dynamics",
    "get_resampler",
    "load_chateau_toml",
    "normalize_log_weights",
    "resample",
    "save_chateau_toml",
    "seir_step",
    "sir_step",
    "uniform_log_weights",
    "weighted_cov",
    "weighted_mean",
]
