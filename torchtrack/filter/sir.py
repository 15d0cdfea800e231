"""Sampling importance resampling (SIR / Condensation) step, batched over targets.

Chateau et al. Fig. 1 and Klein et al. sec. II: (a) resample, (b) predict with the motion
model, (c) weight with the observation likelihood, (d) estimate.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
from torchtrack.filter._random import GeneratorLike
from torchtrack.filter.particles import (
    _capturing,
    best_particle,
    check_particles,
    dominant_mode_mean,
    ess_normalized,
    has_nan_or_posinf,
    normalize_with_lse,
    weighted_mean,
)
from torchtrack.filter.resample import resample

__all__ = [
    "ESTIMATORS",
    "Likelihood",
    "MotionFn",
    "StepResult",
    "check_predicted",
    "evaluate_log_likelihood",
    "get_estimator",
    "sir_step",
]

#: ``likelihood(states (B, M, D)) -> (B, M)``: log-likelihoods (``log_likelihood=True``, the
#: default, numerically safer) or likelihoods >= 0.
Likelihood = Callable[[torch.Tensor], torch.Tensor]
#: ``motion(states (B, N, D), generator) -> (B, N, D)``: e.g. ``KleinAR()``.
MotionFn = Callable[[torch.Tensor, GeneratorLike], torch.Tensor]

ESTIMATORS: dict[str, Callable[[torch.Tensor, torch.Tensor], torch.Tensor]] = {
    "best": best_particle,
    "mean": weighted_mean,
    "mode": dominant_mode_mean,
}


@dataclass
class StepResult:
    """Result of one filter step.

    Attributes:
        states: ``(B, N, D)`` weighted particles after the step.
        log_weights: ``(B, N)`` normalised log-weights.
        estimate: ``(B, D)`` state estimate (weighted mean, best particle or dominant mode).
        ess: ``(B,)`` effective sample size of the returned weights (Jin et al. eq. 11).
        ancestors: ``(B, N)`` int64: particle j descends from input particle ``ancestors[b, j]``.
        resampled: ``(B,)`` bool, rows that were resampled at the start of the step.
        recovered: ``(B,)`` bool, rows whose likelihoods were all zero (log -inf): their weights
            were reset to uniform and the estimate is the mean of the predicted particles.
        log_evidence: ``(B,)`` estimate of ``log p(z_t | z_{1:t-1})`` (``-inf`` where recovered).
        iterations: ``(B,)`` int64 evolutionary iterations (SEIR; 0 for SIR).
    """

    states: torch.Tensor
    log_weights: torch.Tensor
    estimate: torch.Tensor
    ess: torch.Tensor
    ancestors: torch.Tensor
    resampled: torch.Tensor
    recovered: torch.Tensor
    log_evidence: torch.Tensor
    iterations: torch.Tensor


def get_estimator(name: str) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """Estimator by name; ConfigError lists the valid names."""
    try:
        return ESTIMATORS[name]
    except (KeyError, TypeError):
        raise ConfigError(
            f"unknown estimator {name!r}; valid: {', '.join(sorted(ESTIMATORS))}"
        ) from None


def evaluate_log_likelihood(
    likelihood: Likelihood, states: torch.Tensor, log_likelihood: bool, step: str
) -> torch.Tensor:
    """Call ``likelihood`` on ``states (B, M, D)`` and return validated log-likelihoods (B, M).

    Raises:
        ShapeError: the callable returned the wrong shape, or bools or complex numbers.
        FilterError: NaN, ``+inf`` or (for plain likelihoods) negative values; the message names
            ``step``.
    """
    out = likelihood(states)
    if not isinstance(out, torch.Tensor) or out.shape != states.shape[:2]:
        shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ShapeError(
            f"{step}: likelihood must return (B, M) = {tuple(states.shape[:2])}, got {shape}"
        )
    if out.dtype == torch.bool or out.is_complex():
        # bools were log-likelihoods 0 / 1 (or likelihoods 0 / 1), complex values lost their
        # imaginary part with only torch's cast warning
        raise ShapeError(f"{step}: likelihood must return real numbers, got {out.dtype}")
    out = out.to(states.dtype)
    if not log_likelihood:
        # Negative values have no logarithm; checking after log would report them as NaN.
        if bool((out < 0).any()):
            raise FilterError(f"{step}: likelihood must be finite and >= 0 (got negative values)")
        out = torch.log(out)
    if has_nan_or_posinf(out):  # one pass in the common case
        if bool(torch.isnan(out).any()):
            rows = torch.nonzero(torch.isnan(out).any(1)).flatten()[:10].tolist()
            raise FilterError(f"{step}: likelihood returned NaN (batch rows {rows})")
        what = "log-likelihood" if log_likelihood else "likelihood"
        raise FilterError(f"{step}: {what} returned +inf")
    return out


def check_predicted(states: torch.Tensor, step: str) -> None:
    """FilterError unless the states ``(B, N, D)`` a motion model returned are all finite (NaN
    states, given or made by the motion, gave NaN estimates silently). One read from the
    device in the common case; none while a CUDA graph is recorded (checked after replay)."""
    if _capturing(states) or math.isfinite(float(states.sum())):
        return
    bad = ~torch.isfinite(states).flatten(1).all(1)
    if bool(bad.any()):  # a finite sum can also overflow: only then are the entries read
        rows = torch.nonzero(bad).flatten()[:10].tolist()
        raise FilterError(
            f"{step}: the particles after the motion step hold NaN or infinite values (batch "
            f"rows {rows}): check the states given and the motion model"
        )


def _estimate(name: str, fn, states: torch.Tensor, lw: torch.Tensor) -> torch.Tensor:
    """Estimate from normalised ``lw``; the weighted mean skips re-normalisation."""
    if name == "mean":
        return torch.einsum("bn,bnd->bd", lw.exp().to(states.dtype), states)
    return fn(states, lw)


def _gather_states(states: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``states (B, N, D)``, ``idx (B, M)`` -> ``(B, M, D)``.

    Whole rows of D values through one ``index_select`` on the flattened ``(B N, D)`` states:
    the same values as ``torch.gather`` with an expanded index, about 10x faster on CPU at
    (B, N, D) = (100, 1000, 6) (gather walks the expanded index element by element)."""
    b, n, d = states.shape
    m = idx.shape[1]
    flat = idx + (torch.arange(b, device=idx.device, dtype=idx.dtype) * n).unsqueeze(1)
    return states.reshape(b * n, d).index_select(0, flat.reshape(-1)).view(b, m, d)


def sir_step(
    states: torch.Tensor,
    log_weights: torch.Tensor,
    motion: MotionFn,
    likelihood: Likelihood,
    *,
    log_likelihood: bool = True,
    scheme: str = "systematic",
    ess_fraction: float | None = None,
    estimator: str = "mean",
    generator: GeneratorLike = None,
) -> StepResult:
    """One SIR / Condensation step for B targets at once.

    Args:
        states: ``(B, N, D)`` particles of the previous frame.
        log_weights: ``(B, N)`` their log-weights.
        motion: ``motion(states, generator) -> states``, e.g. ``KleinAR()``.
        likelihood: ``(B, N, D) -> (B, N)`` log-likelihoods (or likelihoods if
            ``log_likelihood=False``).
        scheme: resampling scheme name (see ``torchtrack.filter.resample.RESAMPLERS``).
        ess_fraction: None resamples always (Condensation); ``f`` resamples rows with
            ``ESS < f N`` only.
        estimator: ``"mean"`` (Klein eq. 2), ``"best"`` or ``"mode"`` (dominant mode).
        generator: a ``torch.Generator``, a sequence of B generators, or None.

    Returns:
        StepResult.

    Raises:
        ShapeError, ConfigError: bad inputs or names.
        FilterError: the likelihood returned NaN, or the states after the motion step are not
            finite (message names ``sir_step``).
    """
    check_particles(states, log_weights)
    est_fn = get_estimator(estimator)
    ancestors, prior_lw, resampled = resample(
        log_weights, scheme, ess_fraction, generator, step="sir_step"
    )
    predicted = motion(_gather_states(states, ancestors), generator)
    check_particles(predicted, prior_lw)
    check_predicted(predicted, "sir_step")
    ll = evaluate_log_likelihood(likelihood, predicted, log_likelihood, "sir_step")
    joint = prior_lw.to(ll.dtype) + ll
    lw, recovered, log_evidence = normalize_with_lse(joint, step="sir_step")
    return StepResult(
        states=predicted,
        log_weights=lw,
        estimate=_estimate(estimator, est_fn, predicted, lw),
        ess=ess_normalized(lw),
        ancestors=ancestors,
        resampled=resampled,
        recovered=recovered,
        log_evidence=log_evidence,
        iterations=torch.zeros(states.shape[0], dtype=torch.long, device=states.device),
    )
