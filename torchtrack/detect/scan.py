"""Scanning a detector over images: multi-scale sliding windows and non-maximum suppression.

Used for hard-negative mining and for detection (paper section 4.2: the first frame is scanned
over translations and scales). Windows are scored straight from integral images; no image is
resized per scale.

Two paths give the same scores for the same windows:

* **Channel features + boosted trees** (the fast path): channels are computed once per octave
  (:class:`~torchtrack.features.channels.ChannelIntegrals`); for every scale the frame's cell
  lattice is sampled once (:func:`~torchtrack.features.channels.scale_lattice`), every window
  on it reads its features with integer offsets, and the soft cascade of
  :meth:`~torchtrack.learn.BoostedTrees.cascade` drops most windows after a few trees
  (Dollár et al., "The Fastest Pedestrian Detector in the West"; Bourdev & Brandt's soft
  cascade). Window steps are whole cells: ``round(stride * W / cell)`` horizontally and
  ``round(stride * H / cell)`` vertically (at least one cell), times the scale.
* **Anything else** (Chateau's grey Haar bank, stumps, SVMs): every window of
  :func:`sliding_windows` is scored with :meth:`Detector.decision_function`.

Both paths can let windows hang over the frame's edges (``pad``: the border pixels continued,
as Dollár's padded channel pyramids), so objects the edge cuts are still found, and both can
refine the NMS winners by box voting (``vote_iou``, :func:`box_vote`). ``torchtrack detect``
uses both (0.1 and 0.5).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence
from typing import Any

import torch

from torchtrack.boxes import _check_frame_size, xywh_to_xyxy
from torchtrack.errors import ConfigError, ShapeError, is_number

__all__ = [
    "box_vote",
    "nms",
    "scan",
    "scan_batch",
    "scan_scales",
    "scan_window_count",
    "sliding_windows",
]


#: the smallest ratio between successive scan scales: 1.01 already gives ~100 scales an
#: octave; a step just above 1 would ask for millions (a scan that never ends)
MIN_SCALE_STEP = 1.01
#: the smallest window height (pixels) worth suggesting when frames are too small for a scan
MIN_WINDOW_PX = 8
#: the smallest scan scale: the frames are upsampled at most 16x for the window (a person 8 px
#: tall for the 128 px pedestrian model); 0.01 asked for a lattice of tens of GB, 1e-308
#: overflowed the count of scales
MIN_SCALE = 1 / 16


def warn_unit_range(frames: torch.Tensor, stacklevel: int = 3) -> None:
    """Warn (``UserWarning``) when floating-point ``frames`` hold no value above 1 and some
    above 0: the scan reads pixels as 0..255 levels, so frames scaled to [0, 1] (torchvision's
    convention) are scanned as a nearly black frame and yield nothing. A warning, not an
    error: a dark 0..255 frame (every level 0 or 1, a fade to black) looks the same. 8-bit
    frames and an all-zero frame never warn; NaN is left to the pixel check."""
    if not isinstance(frames, torch.Tensor) or not frames.is_floating_point():
        return
    if frames.numel() == 0:
        return
    hi = float(frames.max())
    if 0.0 < hi <= 1.0:
        warnings.warn(
            f"frames {tuple(frames.shape)} are floating point with every value in [0, {hi:g}]: "
            "pixels are read as 0..255 levels, so this is scanned as a nearly black frame "
            "(frames scaled to [0, 1]: multiply by 255 first)",
            UserWarning,
            stacklevel=stacklevel,
        )


def sliding_windows(
    frame_size: tuple[int, int],
    window: tuple[int, int],
    *,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    pad: float = 0.0,
) -> torch.Tensor:
    """All windows of the window's aspect ratio inside a frame, at geometric scales.

    Args:
        frame_size: ``(H, W)`` of the frame.
        window: ``(h, w)`` of the detector window at scale 1.
        scale_step: ratio between successive scales (> 1).
        stride: step between windows as a fraction of the window width (and height) at that
            scale.
        min_scale, max_scale: scale range (default up to the largest that fits).
        pad: windows may reach this fraction of their width (height) beyond the left and
            right (top and bottom) edges of the frame (0: inside the frame).

    Returns:
        ``(N, 4)`` float32 boxes x, y, w, h (empty when the window does not fit).

    Raises:
        ConfigError, ShapeError: as :func:`scan_scales`; a ``stride`` or ``pad`` out of range.
    """
    if not 0.0 < stride <= 1.0:
        raise ConfigError(f"stride must be in (0, 1], got {stride}")
    _check_pad(pad)
    scales = scan_scales(
        frame_size, window, scale_step=scale_step, min_scale=min_scale, max_scale=max_scale
    )
    fh, fw = frame_size
    h, w = window
    if not scales:
        return torch.zeros((0, 4))
    out = []
    for s in scales:
        bw, bh = w * s, h * s
        step_x = max(1.0, stride * bw)
        step_y = max(1.0, stride * bh)
        xs = torch.arange(-pad * bw, fw - bw + pad * bw + 1e-6, step_x)
        ys = torch.arange(-pad * bh, fh - bh + pad * bh + 1e-6, step_y)
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        n = gx.numel()
        out.append(
            torch.stack(
                (gx.reshape(-1), gy.reshape(-1), torch.full((n,), bw), torch.full((n,), bh)), 1
            )
        )
    return torch.cat(out).to(torch.float32)


def nms(
    boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float = 0.3, *, overlap: str = "union"
) -> torch.Tensor:
    """Greedy non-maximum suppression on x, y, w, h boxes.

    Args:
        boxes: ``(N, 4)`` x, y, w, h; scores: ``(N,)``.
        iou_threshold: a box is dropped when its overlap with a kept, higher-scoring box exceeds
            this.
        overlap: ``"union"``: intersection over union (kornia's ``nms``); ``"min"``:
            intersection over the smaller box (Dollár's ``bbNms`` with ``ovrDnm = 'min'``: a
            box lying mostly inside a better one, such as a detection of a person's legs below
            the detection of the person, is dropped even though their IoU is small).

    Returns:
        ``(K,)`` int64 indices of kept boxes, by decreasing score.
    """
    from kornia.geometry.bbox import nms as kornia_nms

    if boxes.ndim != 2 or boxes.shape[-1] != 4 or scores.shape != boxes.shape[:1]:
        raise ShapeError(
            f"nms needs boxes (N, 4) and scores (N,), got {tuple(boxes.shape)} and "
            f"{tuple(scores.shape)}"
        )
    if overlap not in ("union", "min"):
        raise ConfigError(f"nms overlap must be 'union' or 'min', got {overlap!r}")
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=boxes.device)
    if overlap == "union":
        # kornia loops over kept boxes only and never builds the N x N IoU matrix (N can be
        # tens of thousands of windows when no threshold is applied).
        return kornia_nms(xywh_to_xyxy(boxes.float()), scores, iou_threshold).to(torch.int64)
    order = scores.argsort(descending=True)
    b = boxes[order].to(torch.float64)
    x1, y1 = b[:, 0], b[:, 1]
    x2, y2 = x1 + b[:, 2], y1 + b[:, 3]
    area = b[:, 2] * b[:, 3]
    alive = torch.ones(b.shape[0], dtype=torch.bool, device=b.device)
    keep = []
    for i in range(b.shape[0]):  # a loop over kept boxes; the rest is vectorised
        if not bool(alive[i]):
            continue
        keep.append(i)
        iw = (torch.minimum(x2[i], x2) - torch.maximum(x1[i], x1)).clamp_min(0)
        ih = (torch.minimum(y2[i], y2) - torch.maximum(y1[i], y1)).clamp_min(0)
        ov = iw * ih / torch.minimum(area[i], area).clamp_min(1e-12)
        alive &= ov <= iou_threshold
    return order[torch.tensor(keep, dtype=torch.int64, device=b.device)]


def box_vote(
    kept: torch.Tensor,
    boxes: torch.Tensor,
    weights: torch.Tensor,
    vote_iou: float,
    *,
    reference: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """Refine boxes kept by non-maximum suppression with the windows they suppressed.

    Each kept box becomes the weighted mean, in centre and log width / log height, of every
    candidate box that overlaps it by at least ``vote_iou`` (itself included): Dalal's
    mean-shift fusion of detections over position and scale, in the one-step form of box
    voting (Gidaris & Komodakis, ICCV 2015). A dense scan fires on windows a step or a scale
    away from the object, and the single best of them may be one of those: on UIUC's
    multi-scale cars, 13 of the 19 misses at equal error rate were NMS winners one scale step
    (x 1.2) or a stride off the car, and voting found 9 more cars (``docs/detectors.md``).

    Args:
        kept: ``(K, 4)`` x, y, w, h boxes kept by NMS.
        boxes: ``(N, 4)`` every candidate (the kept ones among them).
        weights: ``(N,)`` non-negative votes (calibrated probabilities).
        vote_iou: minimal IoU with a kept box to vote for it, in (0, 1].
        reference: optional ``(kept_ref (K, 4), boxes_ref (N, 4))`` boxes whose IoU decides
            the votes (e.g. the object boxes inside detection windows); default the boxes.

    Returns:
        ``(K, 4)`` voted boxes (float32).
    """
    if not 0.0 < vote_iou <= 1.0:
        raise ConfigError(f"vote_iou must be in (0, 1], got {vote_iou}")
    n = boxes.shape[0] if boxes.ndim == 2 else -1
    shapes_ok = (
        kept.ndim == 2
        and kept.shape[-1] == 4
        and boxes.ndim == 2
        and boxes.shape[-1] == 4
        and weights.shape == (n,)
    )
    if reference is not None:
        shapes_ok = shapes_ok and reference[0].shape == kept.shape
        shapes_ok = shapes_ok and reference[1].shape == boxes.shape
    if not shapes_ok:
        raise ShapeError(
            f"box_vote needs kept (K, 4), boxes (N, 4), weights (N,) (and references of the "
            f"same shapes), got {tuple(kept.shape)}, {tuple(boxes.shape)}, "
            f"{tuple(weights.shape)}"
        )
    if kept.shape[0] == 0 or boxes.shape[0] == 0:
        return kept.to(torch.float32)
    from torchtrack.boxes import box_iou_matrix

    kr, br = reference if reference is not None else (kept, boxes)
    br = br.double()
    vote = weights.double().clamp_min(0)
    b = boxes.double()
    centre = b[:, :2] + 0.5 * b[:, 2:]
    size = b[:, 2:].clamp_min(1e-12).log()
    out = kept.double().clone()
    step = max(1, 4_000_000 // boxes.shape[0])  # bounds the (kept x candidates) overlaps
    for k0 in range(0, kept.shape[0], step):
        w = vote[None] * (box_iou_matrix(kr[k0 : k0 + step].double(), br) >= vote_iou)
        total = w.sum(1, keepdim=True)
        w = w / total.clamp_min(1e-300)
        sz = (w @ size).exp()
        voted = torch.cat((w @ centre - 0.5 * sz, sz), 1)
        # a kept box without any weight (all votes 0) stays as it was
        out[k0 : k0 + step] = torch.where(total > 0, voted, out[k0 : k0 + step])
    return out.to(torch.float32)


def scan_scales(
    frame_size: tuple[int, int],
    window: tuple[int, int],
    *,
    scale_step: float = 1.2,
    min_scale: float = 1.0,
    max_scale: float | None = None,
) -> list[float]:
    """The geometric scales ``min_scale * scale_step ** i`` at which the window fits the frame
    (and ``<= max_scale``).

    Raises:
        ConfigError: ``scale_step`` below :data:`MIN_SCALE_STEP` (a step just above 1 would
            ask for millions of scales: a scan that never ends), or not finite; ``min_scale``
            below :data:`MIN_SCALE` or not finite; ``max_scale`` NaN or below ``min_scale``.
        ShapeError: ``frame_size`` not two finite sizes >= 0 or ``window`` not two finite
            sizes > 0 (bools refused: ``(True, 8)`` was a 1-pixel side).
    """
    _check_frame_size(frame_size)
    _check_frame_size(window, "window", positive=True)
    if not (MIN_SCALE_STEP <= scale_step < math.inf):
        raise ConfigError(
            f"scale_step must be a finite number >= {MIN_SCALE_STEP:g} (a smaller step scans "
            f"hundreds of nearly equal scales), got {scale_step}"
        )
    if not (min_scale > 0 and math.isfinite(min_scale)):
        raise ConfigError(f"min_scale must be a positive number, got {min_scale}")
    if min_scale < MIN_SCALE:
        raise ConfigError(
            f"min_scale must be >= {MIN_SCALE:g} (frames upsampled at most "
            f"{1 / MIN_SCALE:g}x for the window), got {min_scale:g}"
        )
    if max_scale is not None and not max_scale >= min_scale:  # NaN was ignored, silently
        raise ConfigError(
            f"max_scale must be None or a number >= min_scale ({min_scale:g}), got {max_scale}"
        )
    fh, fw = frame_size
    h, w = window
    top = min(fh / h, fw / w)
    if max_scale is not None:
        top = min(top, max_scale)
    if top < min_scale:
        return []
    n = math.floor(math.log(top / min_scale) / math.log(scale_step) + 1e-9) + 1
    return [min_scale * scale_step**i for i in range(n)]


def _check_pad(pad: float) -> None:
    if not (0.0 <= pad <= 0.5 and math.isfinite(pad)):
        raise ConfigError(f"pad must be in [0, 0.5] (a fraction of the window), got {pad}")


def _outside_cells(bank, pad: float) -> tuple[int, int]:
    """``pad`` (a fraction of the window) in whole cells of the lattice: (rows, columns)."""
    hc, wc = bank.grid
    return round(pad * hc), round(pad * wc)


def _pad_frames(frames: torch.Tensor, py: int, px: int) -> torch.Tensor:
    """Frames with their border rows / columns repeated ``py`` / ``px`` times on each side
    (as Dollár's channel pyramids pad: a window hanging over the edge sees the edge continued
    rather than black), in their own dtype: 8-bit frames stay 8-bit, so their colour channels
    are read from the 256-entry table (``features.channels._linear_rgb``), not recomputed."""
    if py == 0 and px == 0:
        return frames
    h, w = frames.shape[-2:]
    dev = frames.device
    rows = torch.arange(-py, h + py, device=dev).clamp_(0, h - 1)
    cols = torch.arange(-px, w + px, device=dev).clamp_(0, w - 1)
    return frames.index_select(-2, rows).index_select(-1, cols)


def scan_window_count(
    detector,
    frame_size: tuple[int, int],
    *,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    pad: float = 0.0,
) -> int:
    """How many windows :func:`scan` scores (before any cascade rejection) on a frame of
    ``frame_size``."""
    _check_pad(pad)
    if not _lattice_capable(detector):
        return int(
            sliding_windows(
                frame_size,
                detector.window,
                scale_step=scale_step,
                stride=stride,
                min_scale=min_scale,
                max_scale=max_scale,
                pad=pad,
            ).shape[0]
        )
    bank = detector.bank
    ky, kx = _outside_cells(bank, pad)
    wh, ww = bank.window
    st_i = max(1, round(stride * wh / bank.cell))
    st_j = max(1, round(stride * ww / bank.cell))
    fh, fw = frame_size
    n = 0
    for s in scan_scales(
        frame_size, bank.window, scale_step=scale_step, min_scale=min_scale, max_scale=max_scale
    ):
        li = math.floor((fh + 2 * ky * bank.cell * s - wh * s) / (bank.cell * s) + 1e-9)
        lj = math.floor((fw + 2 * kx * bank.cell * s - ww * s) / (bank.cell * s) + 1e-9)
        if li >= 0 and lj >= 0:
            n += (li // st_i + 1) * (lj // st_j + 1)
    return n


def _lattice_capable(detector) -> bool:
    from torchtrack.features.channels import ChannelBank

    return isinstance(detector.bank, ChannelBank) and hasattr(detector.classifier, "cascade")


def _rectangle_weights(coef: torch.Tensor) -> torch.Tensor | None:
    """``(K,)`` weights ``w`` when every feature of ``coef (K, P)`` is one rectangle whose four
    corners are weighted ``w * (1, -1, -1, 1)`` (a box mean: ``w`` is one over its area in
    cells; every feature of both bundled models), else None."""
    if coef.shape[1] != 4:
        return None
    w = coef[:, 0]
    return w if bool((coef == w[:, None] * coef.new_tensor([1, -1, -1, 1])).all()) else None


def _combine_corners(v: torch.Tensor, coef: torch.Tensor | None) -> torch.Tensor:
    """Corner values ``v (..., P)`` -> features ``(...)``: ``(v * coef).sum(-1)``, or with
    ``coef = None`` (every feature one rectangle, :func:`_rectangle_weights`) ``((a - b) - c)
    + d``, the rectangle's sum, whose weight the caller applies with its other per-feature
    factors: no coefficient gathered per window and tree (the order in which the CPU's sum adds
    ``v * (1, -1, -1, 1)``, so with weights of 1 the values are the same, bit for bit)."""
    if coef is None:
        a, b, c, d = v.unbind(-1)
        s = a - b
        s -= c  # in place: ((a - b) - c) + d, no temporary per step
        s += d
        return s
    return (v * coef).sum(-1)


#: windows per scoring call and frame when ``batch`` is None: channel models with boosted trees
#: (the lattice path, whose cascade reads at most ``trees._READ_VALUES`` window-features a call
#: whatever the number of windows: a call over a whole PETS frame's 42,536 windows pays the
#: cascade's per-step work once instead of three times, ~4% of a scan, the same margins), and
#: every other model (whose scoring call holds every window's features)
LATTICE_BATCH = 65_536
SCORE_BATCH = 16_384

#: lattice values (float64) scored together in one cascade call: scales are grouped up to this
#: many, so that one call serves most of a frame's scales (the cascade's per-call work is then
#: paid once per group instead of once per scale) while a batch of large frames stays bounded
#: (~64 MiB of lattice per group and frame: a batch of frames groups the same scales as one)
_GROUP_VALUES = 1 << 23


def _scan_lattice(
    detector,
    frames: torch.Tensor,
    scales: list[float],
    stride: float,
    cascade: bool,
    batch: int,
    pad: float = 0.0,
    cascade_threshold: float | None = None,
    keep_windows: Callable[[torch.Tensor], torch.Tensor] | None = None,
    frame_keep: Sequence[Callable[[torch.Tensor], torch.Tensor] | None] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, Any, tuple[int, int]]:
    """Soft-cascade scan of every lattice window: ``(frame index (M,), windows (M, 4),
    margins (M,))`` of the windows that pass the cascade (all windows with ``cascade=False``),
    then the integral images the windows were read from and their padding ``(py, px)``.

    ``frame_keep[b]`` (None: all) then keeps frame ``b``'s windows it accepts, judged on the
    same float64 boxes ``keep_windows`` sees (so a window a single-frame scan with that
    function would skip is dropped here exactly).

    The windows of consecutive scales (lattices of up to :data:`_GROUP_VALUES` values in all)
    are scored by one cascade call; each scale's windows read their own lattice with that
    scale's point offsets and area factors, the values and the arithmetic of one call per scale
    (the same margins, bit for bit)."""
    from torchtrack.features.channels import scale_lattice

    bank, clf = detector.bank, detector.classifier
    ky, kx = _outside_cells(bank, pad)
    s_max = max(scales, default=1.0)
    py, px = math.ceil(ky * bank.cell * s_max), math.ceil(kx * bank.cell * s_max)
    ints = bank.integrals(_pad_frames(frames, py, px))
    dev = frames.device
    pc, pi, pj, coef, lam = bank.padded_points(detector.feature_index, dev)
    # one-rectangle features: their weights join the per-feature factors (same values up to
    # rounding: a weight applied after the corners' sum rather than to each corner)
    rect_w = _rectangle_weights(coef)
    box_only = rect_w is not None
    wh, ww = bank.window
    step = (max(1, round(stride * wh / bank.cell)), max(1, round(stride * ww / bank.cell)))
    nb = frames.shape[0]
    out_f, out_b, out_m = [], [], []

    def score_group(group: list) -> None:
        nc = group[0].channels
        # int32 offsets where every lattice of the group has fewer than 2^31 values (always, at
        # any frame size a scan can hold): half the index traffic of the hottest gather, and
        # 10-30% faster reads on the CPU (the same values)
        small = all(lat.values.numel() < 2**31 for lat in group)
        ix = torch.int32 if small else torch.int64
        bases, offs, factors, starts = [], [], [], [0]
        for lat in group:
            li, lj = lat.shape
            m = lat.origins.shape[0]
            # (K, P) offsets of every feature's points
            offs.append(((pi * lj + pj) * nc + pc).to(ix))
            fac = lat.norm * torch.exp(lat.logr * lam)  # (K,)
            factors.append(fac if rect_w is None else fac * rect_w)
            bases.append(
                (
                    torch.arange(nb, device=dev)[:, None] * (li * lj * nc)
                    + ((lat.origins[:, 0] * lj + lat.origins[:, 1]) * nc)[None, :]
                )
                .reshape(-1)
                .to(ix)
            )  # (B * M,) frame-major, as one call per scale numbers them
            starts.append(starts[-1] + nb * m)
        base = torch.cat(bases)
        bounds = torch.tensor(starts[1:-1], dtype=torch.int64, device=dev)
        # a passing window's scale, frame and box follow from its row: no per-window tables
        first = torch.tensor(starts[:-1], dtype=torch.int64, device=dev)
        per_frame = torch.tensor([lat.origins.shape[0] for lat in group], device=dev)
        box_first = torch.cumsum(per_frame, 0) - per_frame
        box_all = torch.cat([lat.boxes for lat in group])

        def read(rows: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
            # rows are increasing, so each scale's windows are one run of them: read each run
            # with its scale's tables, exactly as one call per scale would
            # f: (A, T) per window, or (T,) shared by every window (broadcast tables)
            cut = torch.searchsorted(rows, bounds).tolist()
            # each run's float64 features times their factors, rounded to float32 as they are
            # written into its rows (the product's float32 rounding: (v * fac).to(float32))
            out = torch.empty((rows.shape[0], f.shape[-1]), dtype=torch.float32, device=dev)
            for g, (r0, r1) in enumerate(zip([0, *cut], [*cut, rows.shape[0]], strict=True)):
                if r1 == r0:
                    continue
                fg = f[r0:r1] if f.ndim == 2 else f
                off = offs[g]
                idx = base.index_select(0, rows[r0:r1])[:, None, None] + (
                    off[fg] if fg.ndim == 2 else off.index_select(0, fg)[None]
                )
                # index_select on the flat indices: the same values as values[idx], ~2x faster
                # on CPU than advanced indexing (the scan's hottest gather)
                v = group[g].values.index_select(0, idx.view(-1)).view(idx.shape)
                v = _combine_corners(v, None if box_only else coef[fg])  # (A, T)
                torch.mul(v, factors[g][fg], out=out[r0:r1])
            return out

        total = base.shape[0]
        for r0 in range(0, total, batch):
            n_chunk = min(batch, total - r0)

            def read_chunk(rows, f, r0=r0):
                return read(rows + r0, f)

            rows, marg = clf.cascade(
                read_chunk, n_chunk, device=dev, reject=cascade, reject_at_most=cascade_threshold
            )
            rows = rows + r0
            g = torch.searchsorted(bounds, rows, right=True)
            local, m = rows - first[g], per_frame[g]
            out_f.append(local // m)
            out_b.append(box_all[box_first[g] + local % m])
            out_m.append(marg)

    group: list = []
    size = 0
    for s in scales:
        lat = scale_lattice(
            ints, bank, s, step, outside=(ky, kx), frame_pad=(py, px), keep_windows=keep_windows
        )
        if lat is None:
            continue
        # without a cascade every window reads every tree: one scale per call keeps each
        # call's tables small (grouping only saves the cascade's per-call work)
        if group and (not cascade or size + lat.values.numel() > _GROUP_VALUES * nb):
            score_group(group)
            group, size = [], 0
        group.append(lat)
        size += lat.values.numel()
    if group:
        score_group(group)
    if not out_f:
        z = torch.zeros(0, device=dev)
        return z.long(), torch.zeros((0, 4), device=dev), z, ints, (py, px)
    fidx, boxes, marg = torch.cat(out_f), torch.cat(out_b), torch.cat(out_m)
    if frame_keep is not None and any(fk is not None for fk in frame_keep):
        keep = torch.ones(fidx.shape[0], dtype=torch.bool, device=dev)
        for f, fk in enumerate(frame_keep):
            if fk is not None:
                sel = fidx == f
                keep[sel] = fk(boxes[sel]).to(dev)
        fidx, boxes, marg = fidx[keep], boxes[keep], marg[keep]
    return fidx, boxes.to(torch.float32), marg, ints, (py, px)


def _any_keeps(
    keeps: list[Callable[[torch.Tensor], torch.Tensor] | None],
) -> Callable[[torch.Tensor], torch.Tensor] | None:
    """The windows any of ``keeps`` keeps (None when one of them keeps all)."""
    if any(k is None for k in keeps):
        return None

    def keep(boxes: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(boxes.shape[0], dtype=torch.bool, device=boxes.device)
        for k in keeps:
            out |= k(boxes).to(boxes.device)
        return out

    keep.by_row = all(getattr(k, "by_row", False) for k in keeps)  # see scale_lattice
    return keep


def scan(
    detector,
    frame: torch.Tensor,
    *,
    threshold: float | None = 0.5,
    margin: bool = False,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    nms_iou: float | None = 0.3,
    batch: int | None = None,
    cascade: bool = True,
    nms_on: str = "window",
    nms_overlap: str = "union",
    vote_iou: float | None = None,
    pad: float = 0.0,
    cascade_threshold: float | None = None,
    keep_windows: Callable[[torch.Tensor], torch.Tensor] | None = None,
    refine: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Detect by scoring every sliding window of one frame.

    Args:
        detector: a :class:`~torchtrack.detect.Detector`.
        frame: ``(C, H, W)`` or ``(1, C, H, W)``, 0..255 (C = 1 or RGB; scored on luma),
            uint8 or float; a float frame with every value in [0, 1] warns (see
            :func:`warn_unit_range`: it is read as a nearly black 0..255 frame).
        threshold: keep windows scoring at least this (``None``: keep all).
        margin: score with raw classifier margins instead of calibrated probabilities.
        scale_step, stride, min_scale, max_scale: see :func:`sliding_windows`; ``min_scale``
            below 1 scans windows smaller than the training window (objects smaller than the
            training crops: the filters shrink with the box, no image is resized).
        nms_iou: IoU for non-maximum suppression (``None``: no suppression).
        batch: windows per scoring call (bounds memory); None: :data:`LATTICE_BATCH` for
            channel models with boosted trees, :data:`SCORE_BATCH` otherwise.
        cascade: channel detectors with boosted trees: stop evaluating a window when its
            running margin falls below the soft-cascade threshold (rejected windows are not
            returned, also with ``threshold=None``); False scores every window fully.
        nms_on: ``"window"`` or ``"object"``: suppress by the overlap of the windows or of the
            object boxes (:meth:`Detector.window_to_object`); the windows are returned either way.
        nms_overlap: ``"union"`` (IoU) or ``"min"`` (intersection over the smaller box), see
            :func:`nms`.
        vote_iou: refine every kept window with the windows above the threshold that overlap
            it by this IoU (:func:`box_vote`, weighted by calibrated probability, overlaps
            measured like the NMS's: windows or object boxes; each keeps its best window's
            score); ``None``: the NMS winners as they are. Needs ``nms_iou``.
        pad: windows may hang this fraction of their size over each edge of the frame (its
            border pixels continued; channel detectors round it to whole cells): objects cut
            by the edge are still scored with their visible part where the model expects it.
            0: windows inside the frame.
        cascade_threshold: channel detectors with boosted trees: every tree's soft-cascade
            threshold lowered to at most this running margin (a looser cascade: more windows
            survive, more found, slower; never stricter than the model's own); ``None``: the
            model's thresholds. Ignored by detectors without a cascade.
        keep_windows: ``keep_windows(boxes (M, 4)) -> (M,) bool``: only the windows it keeps
            are scored (called once per scale with that scale's windows, in frame
            coordinates): a region of interest, or the sizes that fit a ground plane (the
            multi-target tracker's ``ground_gate``). None: every window.
        refine: move each window the NMS keeps (after the voting) to where the training
            crops put the object, by the detector's :attr:`~Detector.box_regressor` (read on
            the scan's own integral images); no effect on a detector without one, nor without
            ``nms_iou`` (every window as scanned). The scores stay those of the windows as
            scanned.

    Returns:
        ``boxes (K, 4)`` (windows, possibly starting at negative coordinates with ``pad``)
        and ``scores (K,)``, by decreasing score.

    Raises:
        ShapeError: not one frame, or a frame smaller than the window at ``min_scale``.
        DataError: a pixel not finite or outside [0, 255].

    Warns:
        UserWarning: a floating-point frame whose values all lie in [0, 1] (not all 0).
    """
    if not isinstance(frame, torch.Tensor):
        raise ShapeError(
            f"scan takes one frame (C, H, W) or (1, C, H, W), got {type(frame).__name__}"
        )
    if frame.ndim == 3:
        frame = frame[None]
    if frame.ndim != 4 or frame.shape[0] != 1:
        raise ShapeError(
            f"scan takes one frame (C, H, W) or (1, C, H, W), got {tuple(frame.shape)}"
        )
    warn_unit_range(frame)
    return scan_batch(
        detector,
        frame,
        threshold=threshold,
        margin=margin,
        scale_step=scale_step,
        stride=stride,
        min_scale=min_scale,
        max_scale=max_scale,
        nms_iou=nms_iou,
        batch=batch,
        cascade=cascade,
        nms_on=nms_on,
        nms_overlap=nms_overlap,
        vote_iou=vote_iou,
        pad=pad,
        cascade_threshold=cascade_threshold,
        keep_windows=keep_windows,
        refine=refine,
    )[0]


def scan_batch(
    detector,
    frames: torch.Tensor,
    *,
    threshold: float | None = 0.5,
    margin: bool = False,
    scale_step: float = 1.2,
    stride: float = 0.1,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    nms_iou: float | None = 0.3,
    batch: int | None = None,
    cascade: bool = True,
    nms_on: str = "window",
    nms_overlap: str = "union",
    vote_iou: float | None = None,
    pad: float = 0.0,
    cascade_threshold: float | None = None,
    keep_windows: Callable[[torch.Tensor], torch.Tensor]
    | Sequence[Callable[[torch.Tensor], torch.Tensor] | None]
    | None = None,
    refine: bool = True,
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """:func:`scan` over a batch of same-size frames: batched integral images, the same
    windows scored on every frame, then threshold and NMS per frame.

    Args:
        frames: ``(B, C, H, W)``, 0..255. Other arguments as in :func:`scan`; ``batch`` bounds
            the windows scored per call over all frames (``B x N_chunk``; None: B times the
            default of :func:`scan`).
        keep_windows: as in :func:`scan` (one function for every frame), or a sequence of B,
            one per frame (None: all of that frame's windows): the windows any of them keeps
            are scored on every frame, and each frame then keeps those of its own function, before
            the threshold and the NMS. Each frame's result is then the one of :func:`scan` with
            its own function (e.g. each frame's own ground plane,
            :meth:`~torchtrack.track.multi.MultiTargetTracker.detect_batch`).

    Returns:
        B pairs ``(boxes (K_b, 4), scores (K_b,))``, by decreasing score.

    Raises:
        ShapeError: frames not ``(B, C, H, W)``, or smaller than the window at ``min_scale``.
        ConfigError: an argument out of its range (a ``threshold`` outside [0, 1] or NaN, an
            ``nms_iou`` outside [0, 1], a ``stride``, ``pad`` or scale out of range, ...).
    """
    if not isinstance(frames, torch.Tensor) or frames.ndim != 4:
        got = tuple(frames.shape) if isinstance(frames, torch.Tensor) else type(frames).__name__
        raise ShapeError(f"scan_batch takes frames (B, C, H, W), got {got}")
    if frames.shape[1] not in (1, 3):  # before the size check: an (H, W, C) frame came as 'small'
        raise ShapeError(
            f"scan_batch takes frames (B, C, H, W) with C = 1 (gray) or 3 (RGB), got "
            f"{tuple(frames.shape)} (C={frames.shape[1]}); (H, W, C) images: permute(2, 0, 1)"
        )
    if nms_on not in ("window", "object"):
        raise ConfigError(f"nms_on must be 'window' or 'object', got {nms_on!r}")
    if not 0.0 < stride <= 1.0:
        raise ConfigError(f"stride must be in (0, 1], got {stride}")
    if batch is None:
        # an empty batch of frames asked for 0 windows: 'batch must be >= 1, got 0'
        per_frame = LATTICE_BATCH if _lattice_capable(detector) else SCORE_BATCH
        batch = per_frame * max(1, frames.shape[0])
    if batch < 1:
        raise ConfigError(f"batch must be >= 1, got {batch}")
    # NaN kept no window (threshold) or suppressed none (nms_iou), silently; a string or a
    # bool was a TypeError from a comparison (or read as 0 / 1)
    if threshold is not None and not (
        is_number(threshold) and (threshold == threshold if margin else 0.0 <= threshold <= 1.0)
    ):
        raise ConfigError(
            "threshold must be None or "
            + ("a margin (a number, not NaN)" if margin else "a probability in [0, 1]")
            + f", got {threshold!r}"
        )
    if nms_iou is not None and not (is_number(nms_iou) and 0.0 <= nms_iou <= 1.0):
        raise ConfigError(f"nms_iou must be None or in [0, 1], got {nms_iou!r}")
    _check_pad(pad)
    if cascade_threshold is not None and not math.isfinite(cascade_threshold):
        raise ConfigError(f"cascade_threshold must be a finite margin, got {cascade_threshold}")
    if vote_iou is not None:
        if nms_iou is None:
            raise ConfigError("vote_iou refines the boxes kept by NMS: give nms_iou too")
        if not 0.0 < vote_iou <= 1.0:
            raise ConfigError(f"vote_iou must be in (0, 1], got {vote_iou}")
    fh, fw = frames.shape[-2:]
    wh, ww = detector.window
    if fh < wh * min_scale or fw < ww * min_scale:
        fits = min(fh / wh, fw / ww)
        raise ShapeError(
            f"frame {fh}x{fw} (HxW) is smaller than the detector window {wh}x{ww} at the "
            f"smallest scan scale {min_scale:g} ({wh * min_scale:g}x{ww * min_scale:g}); "
            + (
                f"scan with min_scale <= {fits:.3g} or use larger frames"
                if fits * wh >= MIN_WINDOW_PX
                else f"frames this small hold no window of at least {MIN_WINDOW_PX} px: use "
                "larger frames"
            )
        )
    nb = frames.shape[0]
    if nb == 0:  # B pairs for B = 0 frames
        return []
    # the threshold, the NMS and the voting are loops of small reads per frame: off the CPU
    # they run on the host (one copy of the windows there and one of the results back)
    host = frames.device.type != "cpu"
    frame_keep = None
    if keep_windows is not None and not callable(keep_windows):
        frame_keep = list(keep_windows)
        if len(frame_keep) != nb:
            raise ConfigError(
                f"keep_windows gives {len(frame_keep)} functions for {nb} frames: one per frame"
            )
        if nb == 1:  # one frame: its function is the scan's, nothing to filter afterwards
            keep_windows, frame_keep = frame_keep[0], None
        else:
            keep_windows = _any_keeps(frame_keep)
    if _lattice_capable(detector):
        scales = scan_scales(
            (fh, fw),
            detector.window,
            scale_step=scale_step,
            min_scale=min_scale,
            max_scale=max_scale,
        )
        fidx, boxes, marg, ints, (py, px) = _scan_lattice(
            detector,
            frames,
            scales,
            stride,
            cascade,
            batch,
            pad,
            cascade_threshold,
            keep_windows,
            frame_keep,
        )
        scores = marg if margin else detector.proba_from_margin(marg)
        if host:
            fidx, boxes, scores = fidx.cpu(), boxes.cpu(), scores.cpu()
        per_frame = [(boxes[fidx == f], scores[fidx == f]) for f in range(nb)]
    else:
        boxes = sliding_windows(
            (fh, fw),
            detector.window,
            scale_step=scale_step,
            stride=stride,
            min_scale=min_scale,
            max_scale=max_scale,
            pad=pad,
        ).to(frames.device)
        if keep_windows is not None:
            boxes = boxes[keep_windows(boxes).to(boxes.device)]
        # windows reach at most pad x their size over an edge; the largest is s_max x window
        s_max = float(boxes[:, 2].max()) / detector.window[1] if boxes.shape[0] else 0.0
        py = math.ceil(pad * detector.window[0] * s_max - 1e-6)
        px = math.ceil(pad * detector.window[1] * s_max - 1e-6)
        ints = detector.integrals(_pad_frames(frames, py, px))
        scored = boxes + torch.tensor([px, py, 0.0, 0.0], device=boxes.device)
        parts = []
        step = max(1, batch // nb)  # bounds memory: B x step windows per scoring call
        for i in range(0, boxes.shape[0], step):
            b = scored[None, i : i + step].expand(nb, -1, -1)
            s = detector.decision_function(ints, b) if margin else detector.score(ints, b)
            parts.append(s)
        all_scores = (
            torch.cat(parts, 1) if parts else torch.zeros((nb, 0), device=frames.device)
        )  # (B, N)
        if host:
            boxes, all_scores = boxes.cpu(), all_scores.cpu()
        per_frame = [(boxes, all_scores[f]) for f in range(nb)]
        if frame_keep is not None:
            for f, fk in enumerate(frame_keep):
                if fk is not None:
                    k = fk(boxes).to(boxes.device)
                    per_frame[f] = (boxes[k], all_scores[f][k])
    out = []
    for bx, sc in per_frame:
        if threshold is not None:
            keep = sc >= threshold
            bx, sc = bx[keep], sc[keep]
        if nms_iou is not None and bx.shape[0]:
            ref = detector.window_to_object(bx) if nms_on == "object" else bx
            keep = nms(ref, sc, nms_iou, overlap=nms_overlap)
            if vote_iou is not None:
                weights = sc if not margin else detector.proba_from_margin(sc)
                voted = box_vote(bx[keep], bx, weights, vote_iou, reference=(ref[keep], ref))
                out.append((voted, sc[keep]))
                continue
        else:
            keep = sc.argsort(descending=True)
        out.append((bx[keep], sc[keep]))
    if refine and nms_iou is not None and getattr(detector, "box_regressor", None) is not None:
        out = _refined(detector, ints, (py, px), out, frames.device)
    if host:
        out = [(bx.to(frames.device), sc.to(frames.device)) for bx, sc in out]
    return out


def _refined(
    detector, ints: Any, pad: tuple[int, int], out: list, device: torch.device
) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """``out``'s windows moved by the detector's box regressor, read on the scan's integral
    images ``ints`` of the frames padded by ``pad = (py, px)`` (one call for every frame: the
    frames' windows padded to one length)."""
    n = max((bx.shape[0] for bx, _ in out), default=0)
    if n == 0:
        return out
    py, px = pad
    shift = torch.tensor([float(px), float(py), 0.0, 0.0], device=device)
    rows = torch.zeros((len(out), n, 4), dtype=torch.float32, device=device)
    for f, (bx, _) in enumerate(out):
        k = bx.shape[0]
        if k:  # a frame with fewer windows repeats its first (its extra rows are dropped)
            rows[f] = torch.cat((bx, bx[:1].expand(n - k, 4))).to(device=device) + shift
        else:
            wh, ww = detector.window
            rows[f] = torch.tensor([0.0, 0.0, float(ww), float(wh)], device=device) + shift
    moved = detector.refine_windows(ints, rows) - shift
    moved = moved.to(out[0][0].device)
    return [(moved[f, : bx.shape[0]], sc) for f, (bx, sc) in enumerate(out)]
