"""The ground plane of a static scene, learnt from the video's own confident detections.

People (or cars) stand on the ground: with the camera above it and no roll, an object of height
``H`` whose foot point is on image row ``y`` appears ``h = H (y - y_0) / y_c`` pixels tall
(``y_0`` the horizon's row, ``y_c`` the camera's height; Hoiem, Efros and Hebert, "Putting
objects in perspective", CVPR 2006). With object heights alike, the image height is a
straight line in the foot row, ``h = a y + b`` with ``a > 0``: lower in the frame is nearer and
taller. A detection whose height is far from that line is a window the size of a person at the
wrong place: a patch of texture, a part of one person, a group of several.

:class:`GroundPlane` fits that line online, robustly, to the boxes of confirmed, confidently
matched targets, and says how far a box's height is from it as a log ratio. It makes no claim
before it has the evidence: the line is used only once it rests on ``min_samples`` boxes of at
least ``min_targets`` targets whose foot rows spread over at least ``min_spread`` of their
median height, its slope is positive, its residuals' robust spread is at most ``max_sd`` and
at least ``min_inliers`` of the boxes lie within three such spreads of it; a moving or tilting
camera, or objects of very different heights, leave it unfitted (nothing gated). Far
from the rows it was fitted on, the allowance grows with the fit's standard error there (a
regression's prediction interval), so an extrapolated line does not reject what it never saw.

Only the last ``capacity`` boxes are kept: memory is flat and the line follows a camera that
moves slowly.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from torchtrack.errors import ConfigError, ShapeError

__all__ = ["GroundLine", "GroundPlane"]

#: floor of the residuals' robust spread: adults' heights alone vary by about 5% (log sd), so a
#: tighter fit only means the boxes came from a few people
_MIN_SD = 0.05


class GroundLine(NamedTuple):
    """A fitted line ``h = a y + b`` (object height in pixels against foot row), with what its
    prediction interval needs: the robust spread ``sd`` of the log-height residuals and the
    ``n`` inlier foot rows' mean and sum of squared deviations ``sxx``. Immutable and small: a
    snapshot that scans in other processes can use."""

    a: float
    b: float
    sd: float
    n: int
    mean: float
    sxx: float

    def log_ratio(self, boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """How far boxes ``(M, 4)`` x, y, w, h are from the line.

        Returns:
            ``(r, se)``, both ``(M,)`` float64: ``r = log(h / (a y + b))`` at each box's foot
            row ``y = y0 + h`` (NaN where the line predicts no positive height), and the fit's
            standard error of the predicted log height at that row (it grows away from the
            rows the line was fitted on).
        """
        boxes = torch.as_tensor(boxes, dtype=torch.float64).reshape(-1, 4)
        y = boxes[:, 1] + boxes[:, 3]
        pred = self.a * y + self.b
        r = torch.log(boxes[:, 3] / pred.clamp_min(1e-9)).masked_fill(pred <= 0, math.nan)
        se = self.sd * torch.sqrt(1.0 / self.n + (y - self.mean) ** 2 / max(self.sxx, 1e-9))
        return r, se

    def consistent(self, boxes: torch.Tensor, tolerance: float) -> torch.Tensor:
        """``(M,)`` bool: boxes ``(M, 4)`` whose height is within ``tolerance`` (a log ratio)
        of the line, plus three standard errors of the fit at their row."""
        r, se = self.log_ratio(boxes)
        return r.abs() <= tolerance + 3.0 * se  # NaN (no positive height there): False


class GroundPlane:
    """Online robust fit of object height against foot row (see the module notes).

    Args:
        capacity: boxes kept (the most recent).
        min_samples: boxes needed before the line is used.
        min_spread: the foot rows' standard deviation must be at least this fraction of the
            boxes' median height (a line through one row has no slope).
        max_sd: the robust spread (1.4826 MAD) of the log-height residuals above which the
            scene is not a ground plane with objects of one height: the line is not used.
        min_inliers: fraction of the boxes within three robust spreads of the line below which
            the line is not used.
        min_targets: the line's inliers must come from at least this many targets (the
            ``ids`` given to :meth:`add`): two things seen on many frames, false detections of
            a static background say, draw a line too.
    """

    def __init__(
        self,
        capacity: int = 256,
        min_samples: int = 20,
        min_spread: float = 0.1,
        max_sd: float = 0.15,
        min_inliers: float = 0.6,
        min_targets: int = 3,
    ) -> None:
        if not 2 <= int(min_samples) <= int(capacity):
            raise ConfigError(
                f"need 2 <= min_samples <= capacity, got min_samples={min_samples}, "
                f"capacity={capacity}"
            )
        for name, v, ok in (
            ("min_spread", min_spread, min_spread >= 0),
            ("max_sd", max_sd, max_sd > 0),
            ("min_inliers", min_inliers, 0 < min_inliers <= 1),
        ):
            if not (ok and math.isfinite(v)):
                raise ConfigError(f"GroundPlane {name} out of range: {v}")
        self.capacity = int(capacity)
        self.min_samples = int(min_samples)
        self.min_spread = float(min_spread)
        self.max_sd = float(max_sd)
        self.min_inliers = float(min_inliers)
        self.min_targets = max(1, int(min_targets))
        self.reset()

    def reset(self) -> None:
        """Forget every box (a new video)."""
        self._foot = torch.zeros(0, dtype=torch.float64)
        self._height = torch.zeros(0, dtype=torch.float64)
        self._ids = torch.zeros(0, dtype=torch.int64)
        self._anon = 0  # boxes added without ids count as one target each (negative ids)
        #: the line while it is used, else None
        self.line_: GroundLine | None = None

    @property
    def fitted(self) -> bool:
        """True while the line is used."""
        return self.line_ is not None

    def add(self, boxes: torch.Tensor, ids: torch.Tensor | None = None) -> None:
        """Remember object boxes ``(M, 4)`` x, y, w, h in pixels of the targets ``ids (M,)``
        (None: each box its own target); boxes with a non-positive or non-finite height are
        ignored; only the last ``capacity`` are kept."""
        boxes = torch.as_tensor(boxes, dtype=torch.float64).reshape(-1, 4)
        if ids is None:
            ids = -1 - self._anon - torch.arange(boxes.shape[0], dtype=torch.int64)
            self._anon += boxes.shape[0]
        ids = torch.as_tensor(ids, dtype=torch.int64).reshape(-1)
        if ids.shape[0] != boxes.shape[0]:
            raise ShapeError(f"{boxes.shape[0]} boxes but {ids.shape[0]} ids")
        ok = torch.isfinite(boxes).all(1) & (boxes[:, 3] > 0)
        if not bool(ok.any()):
            return
        boxes = boxes[ok]
        self._foot = torch.cat([self._foot, boxes[:, 1] + boxes[:, 3]])[-self.capacity :]
        self._height = torch.cat([self._height, boxes[:, 3]])[-self.capacity :]
        self._ids = torch.cat([self._ids, ids[ok]])[-self.capacity :]
        self._refit()

    def _refit(self) -> None:
        self.line_ = None
        y, h = self._foot, self._height
        n = y.shape[0]
        if n < self.min_samples or float(y.std()) < self.min_spread * float(h.median()):
            return
        # Start from Theil and Sen's line (median of the pairwise slopes, then the median
        # intercept: a third of the boxes may be anything), over pairs of boxes whose foot rows
        # differ by a tenth of their height at least (the same person on consecutive frames
        # says nothing about the slope), then least squares in relative terms on the boxes
        # within three robust spreads of it, until the inliers settle.
        i, j = torch.triu_indices(n, n, 1)
        dy = y[j] - y[i]
        far = dy.abs() >= 0.05 * (h[i] + h[j])
        if int(far.sum()) < self.min_samples:
            return
        a = float(((h[j] - h[i])[far] / dy[far]).median())
        b = float((h - a * y).median())
        inl = torch.zeros(n, dtype=torch.bool)
        sd = math.nan
        for it in range(6):
            pred = a * y + b
            if not bool((pred > 0).all()):
                return
            r = torch.log(h / pred)
            sd = max(1.4826 * float((r - r.median()).abs().median()), _MIN_SD)
            new = r.abs() <= 3.0 * sd
            settled = bool((new == inl).all())
            inl = new
            if settled or it == 5 or int(inl.sum()) < self.min_samples:
                break
            w = 1.0 / h[inl]  # residuals relative to the height: close to log ratios
            design = torch.stack([y[inl] * w, w], 1)
            sol = torch.linalg.lstsq(design, torch.ones_like(w)[:, None]).solution[:, 0]
            a, b = float(sol[0]), float(sol[1])
        if int(inl.sum()) < self.min_samples:
            return
        if not (a > 0 and sd <= self.max_sd and float(inl.double().mean()) >= self.min_inliers):
            return
        if int(torch.unique(self._ids[inl]).numel()) < self.min_targets:
            return
        yi = y[inl]
        mean = float(yi.mean())
        sxx = float(((yi - mean) ** 2).sum())
        self.line_ = GroundLine(a, b, sd, int(yi.shape[0]), mean, sxx)

    def log_ratio(self, boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`GroundLine.log_ratio` of the current line; NaN while it is not used."""
        if self.line_ is None:
            n = torch.as_tensor(boxes).reshape(-1, 4).shape[0]
            nan = torch.full((n,), math.nan, dtype=torch.float64)
            return nan, nan.clone()
        return self.line_.log_ratio(boxes)

    def consistent(self, boxes: torch.Tensor, tolerance: float) -> torch.Tensor:
        """:meth:`GroundLine.consistent` of the current line; all True while it is not used."""
        if self.line_ is None:
            return torch.ones(torch.as_tensor(boxes).reshape(-1, 4).shape[0], dtype=torch.bool)
        return self.line_.consistent(boxes, tolerance)

    def __repr__(self) -> str:
        if not self.fitted:
            return f"GroundPlane(unfitted, {self._foot.shape[0]} boxes)"
        ln = self.line_
        return f"GroundPlane(h = {ln.a:.3f} y + {ln.b:.1f}, sd {ln.sd:.3f}, {ln.n} inliers)"
