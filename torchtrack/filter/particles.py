"""Weighted particle sets: shape checks, log-weight normalisation, ESS and state estimates.

Conventions used throughout ``torchtrack.filter``:

* ``states (B, N, D)``: B independent targets or sequences, N particles, D state dimensions.
* ``log_weights (B, N)``: natural-log importance weights, normalised or not; ``-inf`` is a
  weight of zero. Normalised means ``logsumexp(log_weights, -1) == 0``.
* dtype and device follow ``states``; B = 1 is a single target, not a separate code path.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError, is_integer

__all__ = [
    "ParticleSet",
    "best_particle",
    "check_particles",
    "dominant_mode_mean",
    "ess",
    "ess_normalized",
    "has_nan_or_posinf",
    "normalize_log_weights",
    "normalize_with_lse",
    "uniform_log_weights",
    "weighted_cov",
    "weighted_mean",
]


@dataclass
class ParticleSet:
    """A batch of weighted particle sets.

    Attributes:
        states: ``(B, N, D)`` particle states.
        log_weights: ``(B, N)`` log importance weights (normalised by the filter steps).
    """

    states: torch.Tensor
    log_weights: torch.Tensor

    def __post_init__(self) -> None:
        check_particles(self.states, self.log_weights)

    @classmethod
    def uniform(cls, states: torch.Tensor) -> ParticleSet:
        """Equally weighted particles ``states (B, N, D)``."""
        if not isinstance(states, torch.Tensor) or states.ndim != 3:
            shape = tuple(states.shape) if isinstance(states, torch.Tensor) else type(states)
            raise ShapeError(f"states must be a (B, N, D) tensor, got {shape}")
        return cls(states, uniform_log_weights(states))

    @property
    def weights(self) -> torch.Tensor:
        """``(B, N)`` normalised weights."""
        return normalize_log_weights(self.log_weights)[0].exp()

    def ess(self) -> torch.Tensor:
        """``(B,)`` effective sample size (Jin et al. eq. 11)."""
        return ess(self.log_weights)

    def mean(self) -> torch.Tensor:
        """``(B, D)`` weighted mean (Klein et al. eq. 2)."""
        return weighted_mean(self.states, self.log_weights)


def check_particles(states: torch.Tensor, log_weights: torch.Tensor | None = None) -> None:
    """Raise ShapeError unless ``states`` is ``(B, N, D)`` floating and ``log_weights (B, N)``."""
    if not isinstance(states, torch.Tensor) or states.ndim != 3:
        shape = tuple(states.shape) if isinstance(states, torch.Tensor) else type(states).__name__
        raise ShapeError(f"states must be a (B, N, D) tensor, got {shape}")
    if not states.is_floating_point():
        raise ShapeError(f"states must be floating point (float32 or float64), got {states.dtype}")
    if states.shape[1] == 0:
        raise ShapeError("states must hold at least one particle per batch row (N >= 1), got N=0")
    if log_weights is None:
        return
    if not isinstance(log_weights, torch.Tensor) or log_weights.shape != states.shape[:2]:
        shape = (
            tuple(log_weights.shape)
            if isinstance(log_weights, torch.Tensor)
            else type(log_weights).__name__
        )
        raise ShapeError(
            f"log_weights must have shape (B, N) = {tuple(states.shape[:2])} matching states, "
            f"got {shape}"
        )
    if not log_weights.is_floating_point():
        raise ShapeError(f"log_weights must be floating point, got {log_weights.dtype}")


def _capturing(x: torch.Tensor) -> bool:
    """True while ``x``'s CUDA stream is being captured into a graph (``torch.cuda.graph``),
    where a read back to the host is an error: the value checks are then left to the caller
    (:class:`torchtrack.filter.graph.GraphedSIR` checks the step's output after each replay)."""
    return x.is_cuda and torch.cuda.is_current_stream_capturing()


def has_nan_or_posinf(x: torch.Tensor) -> bool:
    """True if ``x`` holds a NaN or ``+inf`` (``-inf`` is allowed: a zero weight).

    One reduction pass in the common case: a sum is finite or ``-inf`` only when no entry is
    NaN or ``+inf`` (NaN propagates; ``+inf`` alone gives ``+inf``, with ``-inf`` NaN). A
    non-finite sum can also come from overflow, so only then are the entries inspected.
    """
    if _capturing(x):  # a CUDA graph being recorded cannot read back; it checks after replay
        return False
    total = float(x.sum())  # one read from the device
    if math.isfinite(total) or total == -math.inf:
        return False
    return bool((torch.isnan(x) | (x == math.inf)).any())


def uniform_log_weights(states: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` log-weights ``-log N`` for ``states (B, N, D)``, same dtype and device.

    Raises:
        ShapeError: ``states`` not ``(B, N, D)`` floating point with N >= 1 (integer states gave
            -1 for any N, 2-D states were read as N rows, N = 0 a 'math domain error').
    """
    check_particles(states)
    b, n = states.shape[:2]
    return torch.full((b, n), -math.log(n), dtype=states.dtype, device=states.device)


def normalize_log_weights(
    log_weights: torch.Tensor, step: str = "normalize_log_weights"
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normalise log-weights row-wise with log-sum-exp; rows with no mass restart uniform.

    Args:
        log_weights: ``(B, N)`` unnormalised log-weights; ``-inf`` entries are zero weights.
        step: name of the calling step, used in error messages.

    Returns:
        ``(normalized (B, N), recovered (B,) bool)``: ``recovered[b]`` is True where row b had
        no finite weight (all ``-inf``: every likelihood zero) and was reset to ``-log N``.

    Raises:
        FilterError: a log-weight is NaN or ``+inf`` (weights cannot be normalised).
    """
    normalized, recovered, _ = normalize_with_lse(log_weights, step)
    return normalized, recovered


def normalize_with_lse(
    log_weights: torch.Tensor, step: str = "normalize_log_weights"
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``normalize_log_weights`` that also returns the row log-sum-exp ``(B,)`` (``-inf`` for
    recovered rows): the log of the total unnormalised weight, e.g. a log-evidence."""
    if not isinstance(log_weights, torch.Tensor) or log_weights.ndim != 2:
        got = (
            tuple(log_weights.shape)
            if isinstance(log_weights, torch.Tensor)
            else type(log_weights).__name__
        )
        raise ShapeError(f"{step}: log_weights must be (B, N), got {got}")
    # N = 0 restarted its rows at -log(0) (Python's ValueError 'math domain error'); bool
    # weights reached torch's subtraction (RuntimeError)
    if log_weights.shape[1] == 0 or log_weights.dtype == torch.bool:
        raise ShapeError(
            f"{step}: log_weights must be (B, N) numbers with N >= 1, got "
            f"{tuple(log_weights.shape)} {log_weights.dtype}"
        )
    if has_nan_or_posinf(log_weights):
        bad = torch.isnan(log_weights) | (log_weights == math.inf)
        rows = torch.nonzero(bad.any(1)).flatten()[:10].tolist()
        raise FilterError(
            f"{step}: log-weights contain NaN or +inf in batch rows {rows} "
            "(likelihoods must be finite and non-negative)"
        )
    lse = torch.logsumexp(log_weights, dim=1, keepdim=True)
    recovered = torch.isneginf(lse).squeeze(1)
    # On the CPU the common case (no row to restart) skips the selection passes; elsewhere
    # they run always, so that the host need not wait for the device to decide.
    if log_weights.device.type == "cpu" and not bool(recovered.any()):
        return log_weights - lse, recovered, lse.squeeze(1)
    # Rows with zero total mass: subtracting -inf would give NaN; reset them to uniform.
    n = log_weights.shape[1]
    safe_lse = torch.where(recovered.unsqueeze(1), torch.zeros_like(lse), lse)
    normalized = torch.where(
        recovered.unsqueeze(1),
        torch.full_like(log_weights, -math.log(n)),
        log_weights - safe_lse,
    )
    return normalized, recovered, lse.squeeze(1)


def ess(log_weights: torch.Tensor) -> torch.Tensor:
    """Effective sample size ``1 / sum_i w_i^2`` of the normalised weights (Jin et al. eq. 11-12).

    Args:
        log_weights: ``(B, N)``, normalised or not.

    Returns:
        ``(B,)`` in ``[1, N]``; a row with no mass counts as uniform (ESS = N).
    """
    lw, _ = normalize_log_weights(log_weights, step="ess")
    return ess_normalized(lw)


def ess_normalized(lw: torch.Tensor) -> torch.Tensor:
    """ESS of already normalised log-weights ``(B, N)`` (no checks): ``(B,)``."""
    # 1 / sum w^2 = exp(-logsumexp(2 log w)), stable for tiny weights.
    return torch.exp(-torch.logsumexp(2.0 * lw, dim=1))


def weighted_mean(states: torch.Tensor, log_weights: torch.Tensor) -> torch.Tensor:
    """Weighted mean of the particles (Klein et al. eq. 2).

    Args:
        states: ``(B, N, D)``.
        log_weights: ``(B, N)``, normalised or not.

    Returns:
        ``(B, D)``.
    """
    check_particles(states, log_weights)
    w = normalize_log_weights(log_weights, step="weighted_mean")[0].exp()
    return torch.einsum("bn,bnd->bd", w.to(states.dtype), states)


def weighted_cov(states: torch.Tensor, log_weights: torch.Tensor) -> torch.Tensor:
    """Weighted covariance ``sum_i w_i (x_i - m)(x_i - m)^T``: ``(B, N, D)`` -> ``(B, D, D)``."""
    check_particles(states, log_weights)
    w = normalize_log_weights(log_weights, step="weighted_cov")[0].exp().to(states.dtype)
    m = torch.einsum("bn,bnd->bd", w, states)
    c = states - m.unsqueeze(1)
    return torch.einsum("bn,bnd,bne->bde", w, c, c)


def best_particle(states: torch.Tensor, log_weights: torch.Tensor) -> torch.Tensor:
    """The highest-weight particle of each row: ``(B, N, D)`` -> ``(B, D)``.

    Raises:
        FilterError: a log-weight is NaN or ``+inf`` (argmax took a NaN as the largest).
    """
    check_particles(states, log_weights)
    if has_nan_or_posinf(log_weights):  # one reduction; normalize_log_weights' message
        normalize_log_weights(log_weights, step="best_particle")
    idx = log_weights.argmax(dim=1)
    return states[torch.arange(states.shape[0], device=states.device), idx]


def _check_bandwidth(bandwidth: torch.Tensor | float, states: torch.Tensor) -> torch.Tensor:
    """A user's ``bandwidth`` as a ``(B, D)`` tensor of ``states``' dtype and device.

    A number is checked (finite, > 0), and so are the entries of a CPU tensor (no wait on a
    device); a tensor elsewhere is checked for its shape only, and its entries that are not
    > 0 (NaN included) become NaN, so that the estimate is NaN rather than silently made with
    a bandwidth of 1, as it was."""
    b, _, d = states.shape
    if isinstance(bandwidth, (list, tuple)):  # e.g. from a config file: read as a CPU tensor
        try:
            bandwidth = torch.tensor(bandwidth, dtype=torch.float64)
        except (TypeError, ValueError):
            raise ConfigError(
                f"dominant_mode_mean: bandwidth must hold D = {d} numbers, got {bandwidth!r}"
            ) from None
    if isinstance(bandwidth, torch.Tensor):
        shapes = ((), (d,), (b, d))
        if bandwidth.dtype == torch.bool or bandwidth.is_complex() or bandwidth.shape not in shapes:
            raise ShapeError(
                f"dominant_mode_mean: bandwidth must be a number or a (), (D,) = ({d},) or "
                f"(B, D) = ({b}, {d}) tensor of real numbers, got {tuple(bandwidth.shape)} "
                f"{bandwidth.dtype}"
            )
        on_cpu = bandwidth.device.type == "cpu"
        if on_cpu and not bool(((bandwidth > 0) & torch.isfinite(bandwidth)).all()):
            raise ConfigError(
                "dominant_mode_mean: bandwidth must be finite and > 0 (kernel standard "
                f"deviations in state units), got {bandwidth.tolist()}"
            )
        h = bandwidth.to(dtype=states.dtype, device=states.device)
        if not on_cpu:
            h = torch.where(h > 0, h, torch.full_like(h, math.nan))
    elif (
        isinstance(bandwidth, bool)
        or not isinstance(bandwidth, numbers.Real)
        or not 0.0 < float(bandwidth) < math.inf
    ):
        raise ConfigError(
            "dominant_mode_mean: bandwidth must be None, a finite number > 0 or a tensor, "
            f"got {bandwidth!r}"
        )
    else:
        h = torch.full((), float(bandwidth), dtype=states.dtype, device=states.device)
    return h.expand(b, d)


def dominant_mode_mean(
    states: torch.Tensor,
    log_weights: torch.Tensor,
    bandwidth: torch.Tensor | float | None = None,
    n_starts: int = 8,
    iters: int = 10,
) -> torch.Tensor:
    """Robust estimate for multi-modal posteriors: the mean of the dominant mode.

    Weighted mean shift with a Gaussian kernel, started from the ``n_starts`` highest-weight
    particles of each row; the converged point with the largest weighted kernel density is the
    dominant mode. Unlike the weighted mean it does not land between two modes. Cost
    ``O(B * n_starts * N * D * iters)``, fully vectorised.

    Args:
        states: ``(B, N, D)``.
        log_weights: ``(B, N)``.
        bandwidth: kernel standard deviation per state dimension, a float, a ``(D,)`` or a
            ``(B, D)`` tensor in state units. Default: Silverman's rule on the weighted standard
            deviation, ``std_d * ESS ** (-1 / (D + 4))``.
        n_starts: number of starting particles per row, an integer >= 1.
        iters: mean-shift iterations, an integer >= 0.

    Returns:
        ``(B, D)``.

    Raises:
        ShapeError: bad ``states`` / ``log_weights``, or a ``bandwidth`` tensor that is not
            ``()``, ``(D,)`` or ``(B, D)`` real numbers.
        ConfigError: ``n_starts`` or ``iters`` not such an integer; a float ``bandwidth``, or
            an entry of a CPU ``bandwidth`` tensor, that is not finite and > 0. The entries of
            a tensor on another device are not read back (no host synchronisation): there a
            bad entry gives NaN in the result instead.
    """
    check_particles(states, log_weights)
    b, n, d = states.shape
    # n_starts=0 was argmax's IndexError on an empty dimension, a negative iters ran none
    for name, value, least in (("n_starts", n_starts, 1), ("iters", iters, 0)):
        if not is_integer(value) or value < least:
            raise ConfigError(
                f"dominant_mode_mean: {name} must be an integer >= {least}, got {value!r}"
            )
    h = None if bandwidth is None else _check_bandwidth(bandwidth, states)
    lw = normalize_log_weights(log_weights, step="dominant_mode_mean")[0].to(states.dtype)
    if h is None:
        var = torch.diagonal(weighted_cov(states, lw), dim1=1, dim2=2)
        factor = ess(lw).to(states.dtype).pow(-1.0 / (d + 4)).unsqueeze(1)
        h = var.clamp_min(0).sqrt() * factor
        # Dimensions with no spread: any positive bandwidth keeps the kernel finite.
        h = torch.where(h > 0, h, torch.ones_like(h))
    k = min(int(n_starts), n)
    start = lw.topk(k, dim=1).indices
    x = torch.gather(states, 1, start.unsqueeze(-1).expand(b, k, d))  # (B, K, D)
    z = states / h.unsqueeze(1)  # (B, N, D) in bandwidth units

    def log_kernel(x: torch.Tensor) -> torch.Tensor:
        # (B, K, N): log w_i - |x_k - s_i|^2 / 2 in bandwidth units
        return lw.unsqueeze(1) - 0.5 * torch.cdist(x / h.unsqueeze(1), z).square()

    for _ in range(int(iters)):
        a = torch.softmax(log_kernel(x), dim=2)
        x = torch.bmm(a, states)
    density = torch.logsumexp(log_kernel(x), dim=2)  # (B, K)
    best = density.argmax(dim=1)
    return x[torch.arange(b, device=states.device), best]
