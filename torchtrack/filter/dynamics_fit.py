"""Least-squares fit of Chateau et al.'s AR dynamics (eq. 4) from annotated tracks.

Chateau et al. sec. 2.3: "Matrices A, B and Sigma can be estimated from a set of sequences for
which the position of the object is known." With the state ``X_t = (c_t, c_{t-1}, s_t,
s_{t-1})`` the lagged slots of ``X_{t+1}`` are exact copies of ``c_t`` and ``s_t``, so only the
three rows that produce ``(c_{t+1}, s_{t+1})`` are free: they are regressed by least squares on
the full ``X_t`` (no intercept, as in eq. 4). ``B`` injects the noise into those three rows and
``Sigma`` is the residuals' covariance (divided by ``M - 6`` degrees of freedom).

Scale: ``s = sqrt(w h / (w_ref h_ref))`` where the reference is the first annotated box of each
track (``window=None``, so ``s_0 = 1``) or a fixed reference window (eq. 3's W).

Annotation jitter: hand labels move by a pixel or two from frame to frame even when the object
does not. Under constant velocity the residual of ``c`` is a second difference, so a label
jitter of standard deviation ``j`` adds ``6 j^2`` to its variance and ``-4 j^2`` to its lag-1
autocovariance (``2 j^2`` and ``-j^2`` for the first difference of ``s``); the plain residual
covariance mistakes that jitter for motion noise (on the bundled tracks: 4 px per frame, most
of it labels). ``noise="jitter_corrected"`` removes it with those two moments, per track, and
takes the median over tracks, so that a few hand-held or fast sequences do not set the noise of
every other target; the noise of the centre is isotropic (the mean of the x and y variances:
twelve tracks do not tell the two axes apart).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import torch

from torchtrack.errors import ConfigError, DataError
from torchtrack.filter.motion import ChateauAR, check_window, default_chateau_B

__all__ = [
    "ChateauFit",
    "chateau_states",
    "fit_chateau_dynamics",
    "load_chateau_toml",
    "save_chateau_toml",
]

_FREE = [0, 1, 4]  # rows of X_{t+1} that are not copies: cx_{t+1}, cy_{t+1}, s_{t+1}


@dataclass
class ChateauFit:
    """Fitted eq. (4) parameters.

    Attributes:
        A: ``(6, 6)``; B: ``(6, 3)``; Sigma: ``(3, 3)`` (float64).
        n_transitions: number of ``(X_t, X_{t+1})`` pairs used.
        n_tracks: number of tracks that contributed at least one pair.
        rms: ``(3,)`` root mean square one-step residual of cx, cy (pixels) and s.
        A_stderr: ``(6, 6)`` least-squares standard errors of A's free rows (0 elsewhere):
            ``sqrt(Sigma_kk [(X^T X)^-1]_jj)``. Entries multiplying nearly collinear
            regressors (c_t and c_{t-1}, s_t and s_{t-1}) are the least determined.
    """

    A: torch.Tensor
    B: torch.Tensor
    Sigma: torch.Tensor
    n_transitions: int
    n_tracks: int
    rms: torch.Tensor
    A_stderr: torch.Tensor

    def model(self, window: tuple[float, float] = (1.0, 1.0)) -> ChateauAR:
        """A ``ChateauAR`` with these parameters and reference ``window``."""
        return ChateauAR(self.A, self.B, self.Sigma, window=window)


def chateau_states(
    boxes: torch.Tensor, window: tuple[float, float] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """States of one track and a validity mask.

    Args:
        boxes: ``(T, 4)`` x, y, w, h per frame; a row with any NaN is an absent target.
        window: reference ``(w, h)``; None uses the track's first valid box.

    Returns:
        ``(states (T, 6), valid (T,) bool)``: ``valid[t]`` when frames t-1 and t are annotated
        (``states[0]`` is never valid: it has no previous frame).
    """
    if window is not None:  # NaN, negative or bool windows gave NaN or wrong scales silently
        window = check_window(window, "chateau_states")
    boxes = torch.as_tensor(boxes)
    if boxes.dtype == torch.bool or boxes.is_complex():  # bools were 0 / 1 pixel boxes
        raise DataError(f"a track must be (T, 4) real numbers x, y, w, h, got {boxes.dtype}")
    boxes = boxes.to(torch.float64)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise DataError(f"a track must be (T, 4) x, y, w, h, got {tuple(boxes.shape)}")
    if bool(torch.isinf(boxes).any()):  # NaN is an absent target; inf was taken as one too
        raise DataError("a track has an infinite value (a NaN row is an absent target)")
    present = torch.isfinite(boxes).all(1)
    if bool(present.any()) and bool((boxes[present, 2:] <= 0).any()):
        raise DataError("a track has a box with w <= 0 or h <= 0")
    if window is None:
        if not bool(present.any()):
            return boxes.new_zeros(boxes.shape[0], 6), torch.zeros_like(present)
        first = boxes[present][0]
        ref = float(first[2] * first[3])
    else:
        ref = float(window[0]) * float(window[1])
    c = boxes[:, :2] + boxes[:, 2:] / 2
    s = torch.sqrt(boxes[:, 2] * boxes[:, 3] / ref)
    c_prev = torch.cat([c[:1], c[:-1]])
    s_prev = torch.cat([s[:1], s[:-1]])
    states = torch.stack([c[:, 0], c[:, 1], c_prev[:, 0], c_prev[:, 1], s, s_prev], 1)
    valid = present & torch.cat([present.new_zeros(1), present[:-1]])
    return torch.nan_to_num(states), valid


def fit_chateau_dynamics(
    tracks: list[torch.Tensor],
    window: tuple[float, float] | None = None,
    structure: str = "free",
    noise: str = "residual",
) -> ChateauFit:
    """Fit A, B, Sigma of eq. (4) by least squares over all tracks.

    Args:
        tracks: list of ``(T_i, 4)`` box tracks (x, y, w, h; NaN rows = target absent; a
            transition touching an absent frame is skipped).
        window: reference window for the scale (see module docstring).
        structure: ``"free"``: the three free rows of A by least squares (eq. 4 as in the
            paper); ``"constant_velocity"``: A fixed to constant velocity on c and a random
            walk on s (:func:`~torchtrack.filter.motion.default_chateau_A`), only Sigma fitted
            from its residuals. Annotation jitter of single-frame labels biases a free fit
            towards damped or even reversed velocities (the noise of ``c_t - c_{t-1}`` is
            anti-correlated from frame to frame); the fixed structure keeps the motion of a
            walking person and learns only how much it varies.
        noise: ``"residual"``: Sigma is the residuals' covariance; ``"jitter_corrected"``
            (``constant_velocity`` only): a diagonal Sigma with the annotation jitter removed,
            the median over tracks (module notes; tracks with fewer than
            ``_MIN_JITTER_PAIRS`` consecutive residual pairs do not vote).

    Returns:
        ChateauFit.

    Raises:
        DataError: fewer than 12 usable transitions (6 regressors need a margin), or bad boxes
            (bools, or an infinite value).
        ConfigError: ``window`` not None or two finite numbers > 0.
    """
    if window is not None:
        window = check_window(window, "fit_chateau_dynamics")
    xs, ys = [], []
    used = 0
    for tr in tracks:
        st, valid = chateau_states(tr, window)
        pair = valid[:-1] & valid[1:]  # X_t and X_{t+1} both valid: frames t-1, t, t+1
        if bool(pair.any()):
            xs.append(st[:-1][pair])
            ys.append(st[1:][pair][:, _FREE])
            used += 1
    m = sum(x.shape[0] for x in xs)
    if m < 12:
        raise DataError(
            f"fit_chateau_dynamics needs at least 12 transitions (three consecutive annotated "
            f"frames each), got {m}"
        )
    if structure not in ("free", "constant_velocity"):
        raise ConfigError(f"structure must be 'free' or 'constant_velocity', got {structure!r}")
    if noise not in ("residual", "jitter_corrected"):
        raise ConfigError(f"noise must be 'residual' or 'jitter_corrected', got {noise!r}")
    if noise == "jitter_corrected" and structure != "constant_velocity":
        raise ConfigError("noise='jitter_corrected' needs structure='constant_velocity'")
    x = torch.cat(xs)
    y = torch.cat(ys)
    if structure == "constant_velocity":
        from torchtrack.filter.motion import default_chateau_A

        a = default_chateau_A().to(x.device)
        resid = y - x @ a[_FREE].T
        sigma = resid.T @ resid / m
        if noise == "jitter_corrected":
            sigma = _jitter_corrected_sigma(tracks, window, a)
        return _fit_result(a, resid, sigma, torch.zeros(6, 6, dtype=x.dtype, device=x.device), used)
    # Column scaling: positions (hundreds of pixels) and scales (~1) differ by orders of
    # magnitude; scaling the regressors keeps the least-squares problem well conditioned.
    col = x.abs().amax(0).clamp_min(1e-12)
    theta = torch.linalg.lstsq(x / col, y, driver="gelsd").solution / col.unsqueeze(1)  # (6, 3)
    resid = y - x @ theta
    sigma = resid.T @ resid / (m - x.shape[1])
    a = torch.zeros(6, 6, dtype=torch.float64, device=x.device)
    a[_FREE] = theta.T
    a[2, 0], a[3, 1], a[5, 4] = 1.0, 1.0, 1.0
    xs_ = x / col
    inv_diag = torch.diagonal(torch.linalg.pinv(xs_.T @ xs_)) / col.square()  # (6,)
    se = torch.zeros(6, 6, dtype=torch.float64, device=x.device)
    se[_FREE] = torch.sqrt(torch.diagonal(sigma).clamp_min(0).unsqueeze(1) * inv_diag.unsqueeze(0))
    return _fit_result(a, resid, sigma, se, used)


_MIN_JITTER_PAIRS = 20
# Residual = second difference of c (jitter: var 6 j^2, lag-1 -4 j^2) and first difference of s
# (var 2 j^2, lag-1 -j^2): motion variance = var + k * lag-1 with k = 6/4 and 2/1.
_JITTER_K = torch.tensor([1.5, 1.5, 2.0], dtype=torch.float64)


def _jitter_corrected_sigma(
    tracks: list[torch.Tensor], window: tuple[float, float] | None, a: torch.Tensor
) -> torch.Tensor:
    """Diagonal Sigma: per track, the residual variance less the annotation jitter's share
    (from the lag-1 autocovariance), floored at 0, the centre's isotropic; the median over
    tracks (module notes)."""
    per_track = []
    for tr in tracks:
        st, valid = chateau_states(tr, window)
        pair = valid[:-1] & valid[1:]
        r = st[1:][:, _FREE] - st[:-1] @ a[_FREE].T  # (T-1, 3); rows where ~pair are junk
        lag = pair[:-1] & pair[1:]  # residuals t and t+1 both valid
        if int(lag.sum()) < _MIN_JITTER_PAIRS:
            continue
        var = r[pair].square().mean(0)
        c1 = (r[:-1][lag] * r[1:][lag]).mean(0)
        v = (var + _JITTER_K.to(c1.device) * c1).clamp_min(0.0)
        per_track.append(torch.stack([v[:2].mean(), v[:2].mean(), v[2]]))
    if not per_track:
        raise DataError(
            f"noise='jitter_corrected' needs a track with at least {_MIN_JITTER_PAIRS} "
            "consecutive residual pairs"
        )
    v = torch.stack(per_track).quantile(0.5, dim=0)  # torch's median() takes the lower one
    # A floor keeps the noise positive definite when the median track moves perfectly evenly.
    return torch.diag(v.clamp_min(1e-6 * float(v.max().clamp_min(1e-12))))


def _fit_result(
    a: torch.Tensor, resid: torch.Tensor, sigma: torch.Tensor, se: torch.Tensor, used: int
) -> ChateauFit:
    return ChateauFit(
        A=a,
        B=default_chateau_B().to(a.device),
        Sigma=0.5 * (sigma + sigma.T),
        n_transitions=int(resid.shape[0]),
        n_tracks=used,
        rms=resid.square().mean(0).sqrt(),
        A_stderr=se,
    )


def _fmt_matrix(m: torch.Tensor) -> str:
    rows = ", ".join("[" + ", ".join(repr(float(v)) for v in r) + "]" for r in m.tolist())
    return f"[{rows}]"


def save_chateau_toml(path: str | os.PathLike, fit: ChateauFit, comment: str = "") -> None:
    """Write the fitted parameters as TOML (atomically): keys A, B, Sigma, plus [fit] stats."""
    from torchtrack.io.atomic import write_text_atomic

    lines = [f"# {ln}" for ln in comment.splitlines()]
    lines += [
        "# Chateau et al. eq. (4): X_{t+1} = A X_t + B v_t, v_t ~ N(0, Sigma)",
        "# state X_t = (cx_t, cy_t, cx_{t-1}, cy_{t-1}, s_t, s_{t-1}); pixels, scale ratio",
        f"A = {_fmt_matrix(fit.A)}",
        f"B = {_fmt_matrix(fit.B)}",
        f"Sigma = {_fmt_matrix(fit.Sigma)}",
        "",
        "[fit]",
        f"n_transitions = {fit.n_transitions}",
        f"n_tracks = {fit.n_tracks}",
        f"rms = [{', '.join(repr(float(v)) for v in fit.rms)}]",
        "",
    ]
    write_text_atomic(path, "\n".join(lines))


def load_chateau_toml(
    path: str | os.PathLike, window: tuple[float, float] = (1.0, 1.0)
) -> ChateauAR:
    """Load a ``ChateauAR`` from a TOML file written by ``save_chateau_toml``.

    Raises:
        ConfigError: unreadable TOML, unknown or missing keys, or bad matrix shapes.
    """
    import tomllib

    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except UnicodeDecodeError:
        raise ConfigError(
            f"dynamics config {os.fspath(path)!r} is not a text (UTF-8 TOML) file"
        ) from None
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"cannot read dynamics config {os.fspath(path)!r}: {e}") from None
    except RecursionError:  # '[[[[...' nested 10^5 deep
        raise ConfigError(
            f"cannot read dynamics config {os.fspath(path)!r}: it nests arrays or tables too "
            "deeply to read"
        ) from None
    data.pop("fit", None)
    try:
        model = ChateauAR.from_params(data, window=window)
    except (ValueError, TypeError) as e:
        if isinstance(e, ConfigError):
            raise ConfigError(f"{os.fspath(path)}: {e}") from None
        raise ConfigError(f"{os.fspath(path)}: bad matrix values: {e}") from None
    if not all(math.isfinite(v) for v in model.A.flatten().tolist()):
        raise ConfigError(f"{os.fspath(path)}: A has non-finite entries")
    return model
