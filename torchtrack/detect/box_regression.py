"""Where the object lies inside a detection window: a linear box regressor on the detector's own
features (the bounding-box regression of Felzenszwalb et al.'s DPM and of R-CNN, here learnt
from the training crops alone).

A sliding-window detector fires on a range of windows around an object: the lattice's stride
and scale step, and a score surface that is flat near its top, leave the kept window a few
pixels and a few percent of scale away from where the training crops put the object. The
regressor reads the selected features of a kept window and predicts how to move and scale it so
that the object sits where it sat in the training crops::

    cx' = cx + dx * w,   cy' = cy + dy * h,   (w', h') = exp(ds) * (w, h)

It is fitted on jittered copies of the positive training windows (each crop's canonical window
moved by up to ``jitter`` and scaled, the shift back to the canonical window as the target), by
ridge regression on standardised features, so it needs no box annotation beyond the crops' own
alignment and never sees a test video. Predictions are clipped to the jitter the regressor was
fitted on, so a window far from any object is never moved further than that.

Example::

    det = load_model("pedestrian")                    # ships with a regressor
    ints = det.integrals(frames)                      # (B, C, H, W) -> integral tables
    better = det.refine_windows(ints, windows)        # (B, N, 4) detection windows
    boxes = det.window_to_object(better)              # the people's boxes
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from torchtrack.errors import ConfigError, DataError, ModelFormatError, ShapeError

__all__ = ["DEFAULT_ALPHA", "DEFAULT_JITTER", "BoxRegressor", "fit_box_regressor", "jitter_windows"]

#: the jitter of the training windows: up to 0.12 of the window's width sideways, 0.06 of its
#: height up or down, and a scale factor within exp(+-0.12) (about one step of the scan's
#: lattice either way: stride 0.08 of the window, scale step 1.15)
DEFAULT_JITTER = (0.12, 0.06, 0.12)
#: ridge penalty on standardised features (chosen by 4-fold cross-validation over the INRIA
#: training crops' source photos: 3e3 to 3e4 give the same residuals, 1e5 worse)
DEFAULT_ALPHA = 1e4


@dataclass(frozen=True)
class BoxRegressor:
    """A linear map from a window's selected features ``(..., K)`` to ``(dx, dy, ds)``.

    Attributes:
        weight: ``(3, K)`` float32 (the features' standardisation folded in).
        bias: ``(3,)`` float32.
        limit: ``(3,)`` the largest ``|dx|``, ``|dy|``, ``|ds|`` applied (the fitting jitter).
        summary: JSON-safe record of the fit (samples, held-out residuals).
    """

    weight: torch.Tensor
    bias: torch.Tensor
    limit: tuple[float, float, float]
    summary: dict[str, Any]

    def __post_init__(self) -> None:
        w, b = self.weight, self.bias
        if not isinstance(w, torch.Tensor) or w.ndim != 2 or w.shape[0] != 3 or w.shape[1] < 1:
            raise ShapeError(f"box regressor weight must be (3, K), got {_shape(w)}")
        if not isinstance(b, torch.Tensor) or tuple(b.shape) != (3,):
            raise ShapeError(f"box regressor bias must be (3,), got {_shape(b)}")
        if not (bool(torch.isfinite(w).all()) and bool(torch.isfinite(b).all())):
            raise ModelFormatError("box regressor weights must be finite")
        lim = tuple(self.limit)
        if len(lim) != 3 or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 1 for v in lim
        ):
            raise ConfigError(f"box regressor limits must be three numbers in (0, 1], got {lim!r}")
        object.__setattr__(self, "weight", w.detach().to(torch.float32).contiguous())
        object.__setattr__(self, "bias", b.detach().to(torch.float32).contiguous())
        object.__setattr__(self, "limit", tuple(float(v) for v in lim))

    @property
    def n_features(self) -> int:
        return int(self.weight.shape[1])

    def predict(self, feats: torch.Tensor) -> torch.Tensor:
        """``(dx, dy, ds) (..., 3)`` of features ``(..., K)``, clipped to :attr:`limit`."""
        if feats.shape[-1] != self.n_features:
            raise ShapeError(
                f"the box regressor reads {self.n_features} features, got shape "
                f"{tuple(feats.shape)}"
            )
        w = self.weight.to(device=feats.device, dtype=torch.float64)
        flat = feats.reshape(-1, feats.shape[-1])
        out = torch.empty((flat.shape[0], 3), dtype=torch.float64, device=feats.device)
        # a row-wise sum of products in float64, not a matrix product: each window's move is
        # the same whatever the batch around it (a scan of B frames equals B scans of one);
        # 1,024 windows at a time bound the products' memory
        for i in range(0, flat.shape[0], 1024):
            out[i : i + 1024] = (flat[i : i + 1024].to(torch.float64)[:, None, :] * w).sum(-1)
        out = out + self.bias.to(feats.device)
        lim = torch.tensor(self.limit, dtype=out.dtype, device=out.device)
        out = out.clamp(-lim, lim).to(torch.float32)
        return out.reshape(*feats.shape[:-1], 3)

    def apply(self, windows: torch.Tensor, feats: torch.Tensor) -> torch.Tensor:
        """Windows ``(..., 4)`` (x, y, w, h) moved and scaled by the prediction of their
        features ``(..., K)``."""
        d = self.predict(feats).to(windows.dtype)
        x, y, w, h = windows.unbind(-1)
        s = torch.exp(d[..., 2])
        cx = x + w / 2 + d[..., 0] * w
        cy = y + h / 2 + d[..., 1] * h
        nw, nh = w * s, h * s
        return torch.stack((cx - nw / 2, cy - nh / 2, nw, nh), -1)

    def to_state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        return (
            {"weight": self.weight, "bias": self.bias},
            {"limit": list(self.limit), "summary": self.summary},
        )

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> BoxRegressor:
        return cls(tensors["weight"], tensors["bias"], tuple(meta["limit"]), meta["summary"])


def _shape(t: Any) -> Any:
    return tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__


def jitter_windows(
    region: tuple[float, float, float, float],
    n: int,
    jitter: tuple[float, float, float],
    generator: torch.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` windows ``(n, 4)`` around ``region`` (x, y, w, h), moved by up to ``jitter[0]`` of
    their width and ``jitter[1]`` of their height and scaled by ``exp(+-jitter[2])`` (uniform),
    and the targets ``(n, 3)`` that take each back to ``region``."""
    x, y, w, h = (float(v) for v in region)
    u = torch.rand((n, 3), generator=generator, dtype=torch.float64) * 2 - 1
    j = torch.tensor(jitter, dtype=torch.float64)
    ds = u[:, 2] * j[2]
    ww, hh = w * torch.exp(ds), h * torch.exp(ds)
    cx = x + w / 2 + u[:, 0] * j[0] * ww
    cy = y + h / 2 + u[:, 1] * j[1] * hh
    windows = torch.stack((cx - ww / 2, cy - hh / 2, ww, hh), 1)
    targets = torch.stack(((x + w / 2 - cx) / ww, (y + h / 2 - cy) / hh, -ds), 1)
    return windows, targets


def _ridge(x: torch.Tensor, y: torch.Tensor, alpha: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Ridge regression on standardised columns of ``x (n, K)``, returned as weights ``(3, K)``
    and bias ``(3,)`` on the raw features (float64)."""
    mu, sd = x.mean(0), x.std(0)
    sd = torch.where(sd > 1e-9, sd, torch.ones_like(sd))  # a constant feature gets no weight
    xs = (x - mu).div_(sd)  # in place: one (n, K) float64 copy, not two
    ym = y.mean(0)
    a = xs.T @ xs + alpha * torch.eye(x.shape[1], dtype=x.dtype)
    coef = torch.linalg.solve(a, xs.T @ (y - ym))  # (K, 3)
    w = (coef / sd[:, None]).T
    return w, ym - w @ mu


def fit_box_regressor(
    det: Any,
    images: torch.Tensor,
    region: tuple[int, int, int, int],
    groups: list[str] | None = None,
    *,
    per_crop: int = 16,
    jitter: tuple[float, float, float] = DEFAULT_JITTER,
    alpha: float = DEFAULT_ALPHA,
    held_out: float = 0.25,
    seed: int = 0,
    chunk: int = 256,
    scales: tuple[float, ...] = (1.0,),
) -> BoxRegressor:
    """Fit a :class:`BoxRegressor` for ``det`` on positive crops.

    Args:
        det: the :class:`~torchtrack.detect.Detector` whose selected features are read.
        images: ``(N, C, H, W)`` uint8 positive crops with context, the object inside
            ``region`` exactly as in training (INRIA: 96x160 crops, region ``(16, 16, 64, 128)``).
        region: the canonical window ``(x, y, w, h)`` inside every crop.
        groups: a source name per crop (a crop and its mirror share one); the held-out
            residuals are measured on ``held_out`` of the groups (every scale of a crop with
            it), then the regressor is refitted on all of them. None: every crop its own group.
        scales: the crops are also read downscaled by each of these (area averaging, the region
            with them), as training reads them (``data.positive_scales``): a window around a
            person 48 px tall sees the blur of its own resolution, not the crop's detail, and a
            regressor fitted at full resolution alone moves it wrongly (half-size PETS 2009:
            docs/multi_target.md).
        per_crop: jittered windows per crop.
        jitter: see :func:`jitter_windows`.
        alpha: ridge penalty on standardised features.
        seed: seeds the jitter and the held-out split.

    Raises:
        DataError: fewer than 8 crops.
        ConfigError: a parameter out of range.
    """
    n = int(images.shape[0]) if isinstance(images, torch.Tensor) and images.ndim == 4 else 0
    if n < 8:
        raise DataError(f"fitting a box regressor needs at least 8 positive crops, got {n}")
    if not (isinstance(per_crop, int) and 1 <= per_crop <= 1024):
        raise ConfigError(f"per_crop must be an integer in [1, 1024], got {per_crop!r}")
    if len(jitter) != 3 or not all(0 < float(v) <= 1 for v in jitter):
        raise ConfigError(f"jitter must be three numbers in (0, 1], got {jitter!r}")
    if not (math.isfinite(alpha) and alpha > 0):
        raise ConfigError(f"alpha must be a positive number, got {alpha!r}")
    if not 0 < held_out < 1:
        raise ConfigError(f"held_out must be in (0, 1), got {held_out!r}")
    scales = tuple(float(q) for q in scales)
    if not scales or not all(0 < q <= 1 for q in scales) or len(set(scales)) != len(scales):
        raise ConfigError(f"scales must be distinct numbers in (0, 1], got {scales!r}")
    names = groups if groups is not None else [str(i) for i in range(n)]
    if len(names) != n:
        raise ConfigError(f"groups names {len(names)} crops, got {n} images")
    from torchtrack.detect.train_channels import _scaled_images, _split_groups

    gen = torch.Generator().manual_seed(int(seed))
    feats, targets = [], []
    for q in scales:
        for i0 in range(0, n, chunk):
            imgs, reg = _scaled_images(images[i0 : i0 + chunk], region, q, "scales")
            b = imgs.shape[0]
            w, t = jitter_windows(reg, b * per_crop, tuple(jitter), gen)
            ints = det.integrals(imgs)
            f = det.features(ints, w.view(b, per_crop, 4).to(torch.float32), check=False)
            feats.append(f.reshape(b * per_crop, -1).double())
            targets.append(t)
    x, y = torch.cat(feats), torch.cat(targets)
    test = _split_groups(names, held_out, gen)  # training's group hold-out
    rows = torch.tensor([names[i] in test for i in range(n)]).repeat_interleave(per_crop)
    rows = rows.repeat(len(scales))
    w, b = _ridge(x[~rows], y[~rows], alpha)
    lim = torch.tensor(jitter, dtype=torch.float64)
    pred = (x[rows] @ w.T + b).clamp(-lim, lim)
    before = y[rows].pow(2).mean(0).sqrt()
    after = (pred - y[rows]).pow(2).mean(0).sqrt()
    w, b = _ridge(x, y, alpha)
    summary = {
        "crops": n,
        "windows": int(x.shape[0]),
        "per_crop": int(per_crop),
        "jitter": [float(v) for v in jitter],
        "alpha": float(alpha),
        "seed": int(seed),
        "scales": list(scales),
        "held_out_groups": len(test),
        "held_out_rms_before": [round(float(v), 5) for v in before],
        "held_out_rms_after": [round(float(v), 5) for v in after],
    }
    return BoxRegressor(w.float(), b.float(), tuple(float(v) for v in jitter), summary)
