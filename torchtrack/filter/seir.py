"""Sequential evolutionary importance resampling (SEIR), Jin et al. sec. 4.2, Algorithm 3.

After the SIR importance-sampling step, while the effective sample size is small (and fewer
than ``max_iter`` rounds ran), each batch row evolves its particle set:

1. COPY (eq. 8): the N current particles;
2. CROSSOVER (eq. 9): N particles ``X_j + mu (X_i - X_j)``, ``mu ~ U(0, 1)``, with i drawn with
   probability proportional to the normalised weight ``w_i`` and j proportional to ``1 - w_j``
   (the paper's ``p(Y|X_i)`` and ``1 - p(Y|X_j)``, read on normalised weights so that any
   likelihood scale works);
3. MUTATION (eq. 10): N particles ``X_i + lambda nu``, ``nu ~ N(0, I)``;
4. SELECTION: N of the 3N particles resampled by weight; the selected particles keep their own
   likelihoods as weights (renormalised), so the ESS measures how even they are.

The likelihood is re-evaluated on the new particles (2N calls' worth per round: COPY reuses
its values). Rows that reach the ESS target stop evolving while others continue.

``StepResult.ancestors`` follows the particles through the rounds: a COPY or MUTATION child
keeps its parent's ancestor, a CROSSOVER child the ancestor of the parent it lies closer to
(``mu >= 0.5``: X_i, else X_j), so per-particle data (Klein et al.'s per-particle observation
models) can still be carried along.
"""

from __future__ import annotations

import math

import torch

from torchtrack.errors import ConfigError, is_integer, is_number
from torchtrack.filter._random import GeneratorLike, rand, randn, subset
from torchtrack.filter.particles import check_particles, ess_normalized, normalize_log_weights
from torchtrack.filter.resample import _cdf, _invert, get_resampler, resample
from torchtrack.filter.sir import (
    Likelihood,
    MotionFn,
    StepResult,
    _estimate,
    _gather_states,
    check_predicted,
    evaluate_log_likelihood,
    get_estimator,
)

__all__ = ["seir_step"]


def _iid_draws(
    weights: torch.Tensor, generator: GeneratorLike, active: torch.Tensor
) -> torch.Tensor:
    """N unsorted i.i.d. indices per row from ``weights (B, N)`` (rows with no mass: uniform)."""
    has = weights.sum(1, keepdim=True) > 0
    w = torch.where(has, weights, torch.ones_like(weights))
    u = rand(tuple(weights.shape), generator, torch.float64, weights.device, active)
    return _invert(_cdf(w), u)


def seir_step(
    states: torch.Tensor,
    log_weights: torch.Tensor,
    motion: MotionFn,
    likelihood: Likelihood,
    *,
    log_likelihood: bool = True,
    ess_target: float = 0.5,
    max_iter: int = 5,
    mutation_std: float | torch.Tensor = 1.0,
    scheme: str = "systematic",
    estimator: str = "mean",
    generator: GeneratorLike = None,
) -> StepResult:
    """One SEIR step (Jin et al. Algorithm 3, steps 2-3) for B targets at once.

    Args:
        states: ``(B, N, D)`` particles of the previous frame.
        log_weights: ``(B, N)`` their log-weights (resampled to equal weights first).
        motion: ``motion(states, generator) -> states``.
        likelihood: ``(B, M, D) -> (B, M)`` log-likelihoods (or likelihoods with
            ``log_likelihood=False``); called with M = N.
        ess_target: evolve while ``ESS < ess_target * N``, in (0, 1].
        max_iter: at most this many evolutionary rounds (the paper's T).
        mutation_std: lambda of eq. (10), a float or a ``(D,)`` tensor in state units.
        scheme: resampling scheme for the initial resampling and for SELECTION.
        estimator: ``"mean"``, ``"best"`` or ``"mode"``.
        generator: a ``torch.Generator``, a sequence of B generators, or None.

    Returns:
        StepResult; ``iterations`` counts the rounds each row ran, ``ess`` is the final ESS.

    Raises:
        ConfigError: bad ``ess_target``, ``max_iter``, scheme or estimator; a
            ``mutation_std`` that is not a finite number >= 0 (the entries of a tensor on the
            CPU are checked; elsewhere only its dtype, no read back from the device).
        FilterError: NaN likelihood, or states after the motion step that are not finite
            (message names ``seir_step``).
    """
    check_particles(states, log_weights)
    # True was a target of 1 and a max_iter of 1 round, 2.5 ran 2 rounds: Python scalars only
    if not is_number(ess_target) or not (0.0 < ess_target <= 1.0):
        raise ConfigError(f"ess_target must be in (0, 1] (a number), got {ess_target!r}")
    if not is_integer(max_iter) or max_iter < 0:
        raise ConfigError(f"max_iter must be >= 0 (an integer), got {max_iter!r}")
    select = get_resampler(scheme)
    est_fn = get_estimator(estimator)
    b, n, d = states.shape
    _check_mutation_std(mutation_std)
    lam = torch.as_tensor(mutation_std, dtype=states.dtype, device=states.device)
    if lam.ndim > 1 or (lam.ndim == 1 and lam.shape[0] != d):
        raise ConfigError(
            f"mutation_std must be a float or a ({d},) tensor, got {tuple(lam.shape)}"
        )

    # Step 2: importance sampling from the equally weighted previous set.
    ancestors, prior_lw, resampled = resample(log_weights, scheme, None, generator, "seir_step")
    x = motion(_gather_states(states, ancestors), generator)
    check_particles(x, prior_lw)
    check_predicted(x, "seir_step")
    ll = evaluate_log_likelihood(likelihood, x, log_likelihood, "seir_step")
    log_evidence = torch.logsumexp(prior_lw + ll, dim=1)
    lw, recovered = normalize_log_weights(ll, step="seir_step")
    e = ess_normalized(lw)
    active = (e < ess_target * n) & ~recovered
    iterations = torch.zeros(b, dtype=torch.long, device=states.device)

    # Step 3: evolutionary importance resampling. Only active rows draw random numbers (with
    # one generator per row, a row's stream then does not depend on the other rows); the
    # likelihood still sees all B rows, because it is tied to the batch layout.
    anc = ancestors
    for _ in range(int(max_iter)):
        rows = torch.nonzero(active).flatten()
        if rows.numel() == 0:
            break
        w = lw.exp()
        i = _iid_draws(w, generator, active)  # CROSSOVER partners ~ w_i
        j = _iid_draws((1.0 - w).clamp_min(0), generator, active)  # ~ 1 - w_j
        mu = rand((b, n, 1), generator, states.dtype, states.device, active)
        xi, xj = _gather_states(x, i), _gather_states(x, j)
        x_cross = xj + mu * (xi - xj)  # eq. (9)
        noise = randn((b, n, d), generator, states.dtype, states.device, active)
        x_mut = x + lam * noise  # eq. (10)
        new = torch.cat([x_cross, x_mut], 1)
        ll_new = evaluate_log_likelihood(likelihood, new, log_likelihood, "seir_step")
        pool = torch.cat([x, new], 1)  # COPY + CROSSOVER + MUTATION: (B, 3N, D)
        pool_ll = torch.cat([ll, ll_new], 1)
        # Ancestry: a crossover child descends from the parent it lies closer to.
        cross_anc = torch.where(
            mu.squeeze(2) >= 0.5, torch.gather(anc, 1, i), torch.gather(anc, 1, j)
        )
        pool_anc = torch.cat([anc, cross_anc, anc], 1)
        pool_lw, _ = normalize_log_weights(pool_ll[rows], step="seir_step")
        pick = torch.zeros(b, n, dtype=torch.long, device=states.device)
        pick[rows] = select(pool_lw.exp(), subset(generator, rows.tolist()), n)  # SELECTION
        x_sel = _gather_states(pool, pick)
        ll_sel = torch.gather(pool_ll, 1, pick)
        lw_sel, _ = normalize_log_weights(ll_sel, step="seir_step")
        a = active.unsqueeze(1)
        x = torch.where(a.unsqueeze(2), x_sel, x)
        ll = torch.where(a, ll_sel, ll)
        lw = torch.where(a, lw_sel, lw)
        anc = torch.where(a, torch.gather(pool_anc, 1, pick), anc)
        iterations += active.long()
        e = ess_normalized(lw)
        active = active & (e < ess_target * n)

    return StepResult(
        states=x,
        log_weights=lw,
        estimate=_estimate(estimator, est_fn, x, lw),
        ess=e,
        ancestors=anc,
        resampled=resampled,
        recovered=recovered,
        log_evidence=log_evidence,
        iterations=iterations,
    )


def _check_mutation_std(mutation_std) -> None:
    """ConfigError unless ``mutation_std`` is a finite number >= 0 or a real tensor of them (a
    NaN one was reported as 'likelihood returned NaN', a string was torch's TypeError, True a
    std of 1; a negative one was taken as its absolute value)."""
    bad = "seir_step: mutation_std must be a finite number >= 0 or a tensor of them, got "
    if isinstance(mutation_std, torch.Tensor):
        if mutation_std.dtype == torch.bool or mutation_std.is_complex():
            raise ConfigError(bad + str(mutation_std.dtype))
        ok = (mutation_std >= 0) & torch.isfinite(mutation_std)
        if mutation_std.device.type == "cpu" and not bool(ok.all()):
            raise ConfigError(bad + str(mutation_std.tolist()))
    elif not is_number(mutation_std) or not 0 <= mutation_std < math.inf:
        raise ConfigError(bad + repr(mutation_std))
