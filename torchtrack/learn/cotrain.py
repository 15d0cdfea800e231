"""Online co-training of a colour and a texture pixel classifier (Jin et al. sec. 3.2-3.3,
Algorithm 2).

Two :class:`~torchtrack.learn.online_boost.OnlineRealBoost` classifiers score every pixel of a
candidate region, one on the colour codes (R, G, B, Y) and one on the texture codes (18 LTP
patterns) of :mod:`torchtrack.features.pixels`. Their maps are fused by voting:

    h_fused(x) = sign(min_i conf_i(x)),   conf_fused(x) = max_i |conf_i(x)| h_fused(x),

so a pixel is object only when both classifiers agree. With ``opening_size > 1`` each
classifier's map is cleaned by a grey-level morphological opening (kornia) before fusing (Jin's
Fig. 5). The default is 1 (no opening): without positive replay (``replay = 0``) a 3x3
opening of the sparse maps left no blob after a few frames (David: target visible in 7% of the
first 60 frames with it, 100% without); with ``replay = 500`` it is harmless but no better
(dev set, first 150 frames: mean AUC 0.458 with the opening, 0.468 without). The connected blob of positive pixels with the highest
accumulated confidence is the object, and the ellipse of the blob's second moments locates it.

Labels for the next update (Algorithm 2 steps 4-5, sec. 3.3):

* positives, only when the blob's accumulated confidence reaches ``accept_ratio`` times a
  running reference (the first frame's blob, then an average of accepted blobs), so occlusions
  do not poison the model: pixels inside the blob's ellipse that the *other* classifier calls
  object (co-training: each classifier is taught by the other);
* negatives, every frame a blob is found: pixels within ``border`` pixels of the candidate
  region's edge.

The labelled dataset (Algorithm 2: "add ... to the labeled dataset", "retrain ... on the updated
labeled data"): each classifier keeps a pool of its labelled positives, the first frame's
(an anchor of at most ``pool_size / 2`` pixels) and a ring of the most recent accepted ones
(``pool_size / 2``). With ``replay > 0`` every update adds ``replay`` positives drawn from the
pool to the frame's own pixels; ``replay = 0`` trains on the current frame's pixels only (the
behaviour before the pool). Why it matters: online boosting trained on one label moves every
selector towards that label. Without replay, a frame whose blob is too weak for new positives
(an occlusion, or just a noisy frame) trains on the border negatives alone; on the dev set a few
such frames turned every pixel of the candidate region negative (Couple from frame 4, David,
Surfer, Freeman1), after which no blob is ever found, the classifiers are never updated again
and the track is lost for good. With ``replay = 500`` the dev-set AUC on the first 150 frames
rose from 0.309 to 0.468 (``docs/benchmarks/cotrain.md``).

``mode="self"`` is the self-trained baseline of Jin's Fig. 8: one classifier on all 22 features
labels its own training pixels.

Single-channel frames (documented fallback): colour classifier on Y only, texture classifier on
the Y-Y pattern pair.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from kornia.morphology import opening

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.pixels import region_features
from torchtrack.filter._random import randint, randperm
from torchtrack.learn._base import check_fitted
from torchtrack.learn.online_boost import OnlineRealBoost

__all__ = ["Blob", "CoTrainer", "PixelMaps", "fuse_confidences", "region_around"]

MODES = ("cotrain", "self")


def fuse_confidences(conf: torch.Tensor) -> torch.Tensor:
    """Jin et al. Algorithm 2 step 2: ``conf (K, ...)`` of K classifiers -> fused ``(...)``,
    ``max_i |conf_i| * sign(min_i conf_i)`` (a zero minimum counts as positive)."""
    label = torch.where(conf.min(0).values >= 0, 1.0, -1.0).to(conf.dtype)
    return conf.abs().max(0).values * label


def region_around(
    centre: tuple[float, float],
    size: tuple[float, float],
    scale: float,
    frame_size: tuple[int, int],
) -> tuple[int, int, int, int] | None:
    """Integer region ``(x0, y0, x1, y1)`` of ``scale`` times the box ``size (w, h)`` centred on
    ``centre (cx, cy)``, clipped to ``frame_size (H, W)``; None when fewer than 3x3 pixels remain
    (the region left the frame)."""
    hh, ww = frame_size
    cx, cy = centre
    hw, hh_ = scale * size[0] / 2, scale * size[1] / 2
    x0, x1 = max(round(cx - hw), 0), min(round(cx + hw), ww)
    y0, y1 = max(round(cy - hh_), 0), min(round(cy + hh_), hh)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    return x0, y0, x1, y1


@dataclass
class PixelMaps:
    """Confidence maps of one candidate region.

    Attributes:
        region: ``(x0, y0, x1, y1)`` frame pixels covered.
        conf: ``(K, h, w)`` per-classifier confidences (K = 2 co-trained, 1 self-trained).
        fused: ``(h, w)`` fused confidence (Algorithm 2 step 2).
        opened: ``(h, w)`` fused map after the morphological opening.
        codes: ``(h*w, F)`` feature codes per classifier (kept for the update), a tuple.
    """

    region: tuple[int, int, int, int]
    conf: torch.Tensor
    fused: torch.Tensor
    opened: torch.Tensor
    codes: tuple[torch.Tensor, ...]


@dataclass
class Blob:
    """The most confident blob (sec. 3.3).

    Attributes:
        centre: ``(cx, cy)`` ellipse centre in frame pixels.
        axes: ``(a, b)`` ellipse semi-axes (2 standard deviations of the blob's pixels).
        angle: ellipse orientation of axis a, radians from the x axis.
        score: accumulated (opened) fused confidence of the blob.
        area: number of pixels.
        mask: ``(h, w)`` bool pixels of the blob in the region.
        ellipse: ``(h, w)`` bool pixels of the region inside the ellipse.
    """

    centre: tuple[float, float]
    axes: tuple[float, float]
    angle: float
    score: float
    area: int
    mask: torch.Tensor
    ellipse: torch.Tensor


def _ellipse_of(
    mask: torch.Tensor,
) -> tuple[tuple[float, float], tuple[float, float], float, torch.Tensor]:
    ys, xs = torch.nonzero(mask, as_tuple=True)
    pts = torch.stack([xs, ys], 1).to(torch.float64)
    mu = pts.mean(0)
    d = pts - mu
    cov = (
        d.T @ d / max(pts.shape[0], 1)
        + torch.eye(2, dtype=torch.float64, device=mask.device) / 12.0
    )
    evals, evecs = torch.linalg.eigh(cov)
    a, b = 2 * evals[1].clamp_min(0).sqrt(), 2 * evals[0].clamp_min(0).sqrt()
    angle = float(torch.atan2(evecs[1, 1], evecs[0, 1]))
    h, w = mask.shape
    yy, xx = torch.meshgrid(
        torch.arange(h, dtype=torch.float64, device=mask.device),
        torch.arange(w, dtype=torch.float64, device=mask.device),
        indexing="ij",
    )
    g = torch.stack([xx - mu[0], yy - mu[1]], -1)  # (h, w, 2)
    m2 = (g @ torch.linalg.inv(cov) * g).sum(-1)
    return (float(mu[0]), float(mu[1])), (float(a), float(b)), angle, m2 <= 4.0


class CoTrainer:
    """Online co-trained pixel classifier (Jin et al. Algorithm 2).

    Args:
        mode: ``"cotrain"`` (colour + texture classifiers teach each other) or ``"self"`` (one
            classifier on all features, self-trained; the paper's baseline).
        n_selectors, n_candidates, eps: :class:`OnlineRealBoost` parameters of each classifier.
        colour_bins: value blocks of the colour features (texture codes use all 256 patterns).
        ltp_threshold: t of the LTP patterns (grey levels).
        opening_size: side of the square structuring element of the opening (1 = none).
        border: width in pixels of the candidate region's edge band whose pixels are negatives.
        accept_ratio: a blob's accumulated confidence must reach this fraction of the running
            reference for its pixels to become positives.
        max_samples: at most this many pixels per label and update (random subset).
        init_passes: training passes over the first frame's labelled pixels.
        texture_blocks: ``"full"`` (256 LTP codes) or ``"riu2"`` (10 blocks).
        replay: positives drawn from the labelled pool into every update (0 = none).
        pool_size: rows of the labelled pool per classifier (half anchor, half recent).

    Raises:
        ConfigError: invalid parameters (at construction).
    """

    def __init__(
        self,
        mode: str = "cotrain",
        n_selectors: int = 10,
        n_candidates: int = 4,
        eps: float = 1e-3,
        colour_bins: int = 32,
        ltp_threshold: float = 5.0,
        opening_size: int = 1,
        border: int = 3,
        accept_ratio: float = 0.5,
        max_samples: int = 1000,
        init_passes: int = 3,
        texture_blocks: str = "full",
        replay: int = 0,
        pool_size: int = 4000,
    ) -> None:
        if mode not in MODES:
            raise ConfigError(f"unknown co-training mode {mode!r}; valid: {', '.join(MODES)}")
        if not (isinstance(opening_size, int) and opening_size >= 1):
            raise ConfigError(f"opening_size must be an integer >= 1, got {opening_size!r}")
        if not (isinstance(border, int) and border >= 1):
            raise ConfigError(f"border must be an integer >= 1, got {border!r}")
        if not (0.0 <= float(accept_ratio)):
            raise ConfigError(f"accept_ratio must be >= 0, got {accept_ratio!r}")
        if not (isinstance(max_samples, int) and max_samples >= 1):
            raise ConfigError(f"max_samples must be an integer >= 1, got {max_samples!r}")
        if not (isinstance(init_passes, int) and init_passes >= 1):
            raise ConfigError(f"init_passes must be an integer >= 1, got {init_passes!r}")
        if not (isinstance(replay, int) and not isinstance(replay, bool) and replay >= 0):
            raise ConfigError(f"replay must be an integer >= 0, got {replay!r}")
        if not (isinstance(pool_size, int) and not isinstance(pool_size, bool) and pool_size >= 2):
            raise ConfigError(f"pool_size must be an integer >= 2, got {pool_size!r}")
        self.mode = mode
        self.colour_bins = colour_bins
        self.ltp_threshold = ltp_threshold
        self.opening_size = opening_size
        self.border = border
        self.accept_ratio = float(accept_ratio)
        self.max_samples = max_samples
        self.init_passes = init_passes
        self.replay = replay
        self.pool_size = pool_size
        if texture_blocks not in ("full", "riu2"):
            raise ConfigError(f"unknown texture_blocks {texture_blocks!r}; valid: full, riu2")
        self.texture_blocks = texture_blocks
        if mode == "cotrain":
            self.classifiers = [
                OnlineRealBoost(n_selectors, n_candidates, colour_bins, eps),
                OnlineRealBoost(n_selectors, n_candidates, 256, eps),
            ]
        else:
            self.classifiers = [OnlineRealBoost(n_selectors, n_candidates, 256, eps)]
        for c in self.classifiers:
            c._check_params()
        self.reference_: float | None = None
        #: per classifier, the labelled positives kept for replay: ``(anchor, recent)`` code
        #: tensors (first frame's positives, then a ring of accepted ones)
        self.pool_: list[list[torch.Tensor]] | None = None

    # -- features ------------------------------------------------------------------------------
    def codes(self, frame: torch.Tensor, region: tuple[int, int, int, int]) -> tuple:
        """Feature codes of the region's pixels for each classifier: a tuple of ``(h*w, F)``."""
        colour, texture = region_features(
            frame, region, self.ltp_threshold, self.colour_bins, self.texture_blocks
        )
        if self.mode == "cotrain":
            return colour, texture
        return (torch.cat([colour, texture], 1),)

    def _sample(self, idx: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        if idx.numel() <= self.max_samples:
            return idx
        perm = randperm(idx.numel(), generator, idx.device)[: self.max_samples]
        return idx[perm]

    def _train(
        self,
        codes: tuple[torch.Tensor, ...],
        pos: list[torch.Tensor],
        neg: torch.Tensor,
        generator: torch.Generator | None,
    ) -> None:
        """Train classifier i on positives ``pos[i]`` and the shared negatives (pixel indices),
        plus ``replay`` positives drawn from its labelled pool."""
        for i, (clf, c, p) in enumerate(zip(self.classifiers, codes, pos, strict=True)):
            p = self._sample(p, generator)
            n = self._sample(neg, generator)
            pc = torch.cat([c[p], self._replayed(i, generator, c)])
            nc = c[n]
            self._fit(clf, pc, nc, generator)

    def _fit(self, clf, pc: torch.Tensor, nc: torch.Tensor, generator) -> None:
        """One :meth:`OnlineRealBoost.partial_fit` on positive codes ``pc`` and negative codes
        ``nc``, each label carrying half the batch's total importance (so a frame's class ratio
        does not tilt the histograms)."""
        n_p, n_n = pc.shape[0], nc.shape[0]
        y = torch.cat([torch.ones(n_p), -torch.ones(n_n)]).to(pc.device)
        half = 0.5 * (n_p + n_n)
        wt = torch.cat(
            [torch.full((n_p,), half / max(n_p, 1)), torch.full((n_n,), half / max(n_n, 1))]
        ).to(pc.device)
        clf.partial_fit(
            torch.cat([pc, nc]), y, sample_weight=wt if n_p and n_n else None, generator=generator
        )

    def _replayed(self, i: int, generator, like: torch.Tensor) -> torch.Tensor:
        """``replay`` positives of classifier i drawn uniformly from its labelled pool."""
        if self.replay == 0 or self.pool_ is None:
            return like[:0]
        pool = torch.cat(self.pool_[i])
        if pool.shape[0] == 0:
            return pool
        pick = randint(0, pool.shape[0], (min(self.replay, pool.shape[0]),), generator, pool.device)
        return pool[pick]

    def _remember(self, i: int, new: torch.Tensor, generator) -> None:
        """Add accepted positives to classifier i's pool (a ring of ``pool_size / 2`` rows after
        the first frame's anchor of at most ``pool_size / 2`` rows)."""
        half = self.pool_size // 2
        if new.shape[0] > half:
            new = new[randperm(new.shape[0], generator, new.device)[:half]]
        anchor, recent = self.pool_[i]
        self.pool_[i] = [anchor, torch.cat([recent, new])[-half:]]

    # -- Algorithm 2 ---------------------------------------------------------------------------
    def init(
        self,
        frame: torch.Tensor,
        box: tuple[float, float, float, float],
        region: tuple[int, int, int, int],
        generator: torch.Generator | None = None,
    ) -> PixelMaps:
        """First frame: pixels inside the ellipse inscribed in ``box`` (x, y, w, h) are
        positives, pixels of ``region`` outside the box negatives; both classifiers are trained
        ``init_passes`` times. Returns the maps of the region after training, and sets the
        blob-confidence reference.

        Raises:
            ShapeError: bad frame. ConfigError: a region outside the frame.
        """
        _check_frame(frame)
        codes = self.codes(frame, region)
        x0, y0, x1, y1 = region
        h, w = y1 - y0, x1 - x0
        bx, by, bw, bh = (float(v) for v in box)
        yy, xx = torch.meshgrid(
            torch.arange(y0, y1, dtype=torch.float64) + 0.5,
            torch.arange(x0, x1, dtype=torch.float64) + 0.5,
            indexing="ij",
        )
        cx, cy = bx + bw / 2, by + bh / 2
        inside = (((xx - cx) / (bw / 2)) ** 2 + ((yy - cy) / (bh / 2)) ** 2) <= 1.0
        outside = (xx < bx) | (xx > bx + bw) | (yy < by) | (yy > by + bh)
        pos = torch.nonzero(inside.flatten()).flatten()
        neg = torch.nonzero(outside.flatten()).flatten()
        if pos.numel() == 0:
            raise ConfigError(f"box {box} holds no pixel of region {region}")
        if neg.numel() == 0:  # the box fills the region: use its edge band
            neg = torch.nonzero(self._border_mask(h, w).flatten()).flatten()
        self.pool_ = None
        for _ in range(self.init_passes):
            self._train(codes, [pos] * len(self.classifiers), neg, generator)
        half = self.pool_size // 2
        anchor = pos
        if anchor.numel() > half:
            anchor = anchor[randperm(anchor.numel(), generator, anchor.device)[:half]]
        self.pool_ = [[c[anchor], c[:0]] for c in codes]
        maps = self._maps(codes, region)
        blob = self.locate(maps)
        self.reference_ = blob.score if blob is not None else float(maps.opened.clamp_min(0).sum())
        return maps

    def _maps(self, codes: tuple[torch.Tensor, ...], region) -> PixelMaps:
        x0, y0, x1, y1 = region
        h, w = y1 - y0, x1 - x0
        conf = torch.stack(
            [c.decision_function(k) for c, k in zip(self.classifiers, codes, strict=True)]
        )
        conf = conf.view(-1, h, w).to(torch.float32)
        fused = fuse_confidences(conf) if conf.shape[0] > 1 else conf[0]
        if self.opening_size > 1:
            # Jin et al. Fig. 5 (d)-(f): each classifier's map is opened, then the maps fuse.
            kernel = torch.ones(self.opening_size, self.opening_size, device=fused.device)
            op = opening(conf.unsqueeze(1), kernel)[:, 0]
            opened = fuse_confidences(op) if op.shape[0] > 1 else op[0]
        else:
            opened = fused
        return PixelMaps(region=region, conf=conf, fused=fused, opened=opened, codes=codes)

    def score(self, frame: torch.Tensor, region: tuple[int, int, int, int]) -> PixelMaps:
        """Algorithm 2 steps 1-2 on a candidate ``region (x0, y0, x1, y1)`` of ``frame``.

        Raises:
            NotFittedError: before :meth:`init`. ShapeError: bad frame.
        """
        check_fitted(self.classifiers[0], "hist_")
        _check_frame(frame)
        return self._maps(self.codes(frame, region), region)

    def locate(self, maps: PixelMaps) -> Blob | None:
        """Sec. 3.3: the connected blob (8-neighbourhood) of positive opened confidence with the
        highest accumulated confidence, and its bounding ellipse; None if there is no blob."""
        opened = maps.opened
        mask = (opened > 0).cpu().numpy().astype(np.uint8)
        n_lab, labels = cv2.connectedComponents(mask, connectivity=8)
        if n_lab <= 1:
            return None
        lab = torch.from_numpy(labels.astype(np.int64)).to(opened.device)
        sums = torch.bincount(
            lab.flatten(), weights=opened.clamp_min(0).flatten().double(), minlength=n_lab
        )
        sums[0] = -1.0
        best = int(torch.argmax(sums))
        bmask = lab == best
        (mx, my), axes, angle, ell = _ellipse_of(bmask.cpu())
        x0, y0 = maps.region[:2]
        return Blob(
            centre=(mx + x0 + 0.5, my + y0 + 0.5),
            axes=axes,
            angle=angle,
            score=float(sums[best]),
            area=int(bmask.sum()),
            mask=bmask,
            ellipse=ell.to(opened.device),
        )

    def _border_mask(self, h: int, w: int) -> torch.Tensor:
        m = torch.zeros(h, w, dtype=torch.bool)
        b = self.border
        m[:b], m[-b:], m[:, :b], m[:, -b:] = True, True, True, True
        return m

    def update(
        self,
        maps: PixelMaps,
        blob: Blob | None,
        generator: torch.Generator | None = None,
        within: tuple[float, float, float, float] | None = None,
    ) -> bool:
        """Algorithm 2 steps 4-5: retrain with the region's edge band as negatives and, when the
        blob is confident enough, its co-labelled pixels as positives. Nothing is learned
        without a blob.

        Args:
            maps, blob: this frame's maps and most confident blob (None: no update).
            generator: random source of the sample subsets.
            within: optional frame box ``(x, y, w, h)`` (the tracker's estimate): positives are
                further restricted to pixels whose centre lies inside it.

        Returns:
            True when positives were added.
        """
        if blob is None:
            return False
        x0, y0, x1, y1 = maps.region
        h, w = y1 - y0, x1 - x0
        neg = torch.nonzero(self._border_mask(h, w).flatten() & ~blob.ellipse.cpu().flatten())
        neg = neg.flatten()
        ref = self.reference_ if self.reference_ is not None else blob.score
        accepted = blob.score >= self.accept_ratio * ref
        ell = blob.ellipse.flatten()
        if within is not None:
            bx, by, bw, bh = (float(v) for v in within)
            xs = torch.arange(x0, x1, dtype=torch.float64, device=ell.device) + 0.5
            ys = torch.arange(y0, y1, dtype=torch.float64, device=ell.device) + 0.5
            box = ((ys >= by) & (ys < by + bh))[:, None] & ((xs >= bx) & (xs < bx + bw))[None, :]
            ell = ell & box.flatten()
        empty = torch.zeros(0, dtype=torch.long)
        if accepted:
            conf = maps.conf.flatten(1)  # (K, h*w)
            if len(self.classifiers) == 2:
                # Co-training: colour learns where texture says object, and vice versa.
                pos = [
                    torch.nonzero(ell & (conf[1] > 0)).flatten().cpu(),
                    torch.nonzero(ell & (conf[0] > 0)).flatten().cpu(),
                ]
            else:
                pos = [torch.nonzero(ell & (conf[0] > 0)).flatten().cpu()]
            self.reference_ = 0.9 * ref + 0.1 * blob.score
            if self.pool_ is not None:
                for i, (c, p) in enumerate(zip(maps.codes, pos, strict=True)):
                    self._remember(i, c[p.to(c.device)], generator)
        else:
            pos = [empty] * len(self.classifiers)
        self._train(maps.codes, pos, neg, generator)
        return bool(accepted)


def _check_frame(frame: torch.Tensor) -> None:
    if not isinstance(frame, torch.Tensor) or frame.ndim != 3 or frame.shape[0] not in (1, 3):
        shape = tuple(frame.shape) if isinstance(frame, torch.Tensor) else type(frame).__name__
        raise ShapeError(f"frame must be a (C, H, W) tensor with C in {{1, 3}}, got {shape}")
