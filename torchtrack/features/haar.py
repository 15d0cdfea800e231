"""The Haar-wavelet bank of Chateau et al. (2006, section 3.1), evaluated from integral images.

Five zero-mean square filters of side ``T = 2^t`` (paper Fig. 2) at three scales and at every
position of the training window:

=========  ==============================================================  ==============
kind       weights inside the T x T square                                 corner points
=========  ==============================================================  ==============
edge_x     left half +1, right half -1 (vertical edges, left/right symmetry)  6
edge_y     top half +1, bottom half -1 (horizontal edges)                    6
diagonal   top-left and bottom-right quarters +1, the other two -1          9
line_x     central vertical band (T/2 wide) +1, the two outer bands -1      8
line_y     central horizontal band (T/2 high) +1, the outer bands -1        8
=========  ==============================================================  ==============

Scales: for a window of ``H x W`` pixels the sizes are the largest power of two not above
``min(H, W)`` and its halves (paper: a 128 x 64 window gives 64, 32, 16). Positions: every
top-left corner ``(y, x)`` with the square inside the window, on a grid of ``stride`` pixels
(paper: dense, stride 1).

**Feature count.** With stride 1 a 128 x 64 window has
``5 * (65*1 + 97*33 + 113*49) = 44,015`` features and a 64 x 64 window
``5 * (1 + 33^2 + 49^2) = 17,455``. The latter is exactly the paper's vehicle count (section 4.1).
The paper's pedestrian count, ``(64 + 96*32 + 112*48) * 5 = 42,560`` (section 3.1), counts
``(H - T) * (W - T)`` positions for the 32 and 16 scales (one position per axis fewer than fit,
i.e. the last row and column of positions are dropped) and 64 for the 64 scale; the two paper
counts cannot both follow one rule, and we keep the rule that reproduces the vehicle count
(every position that fits). See :func:`paper_pedestrian_count`.

**Normalisation.** A feature value is the filter response divided by the filter's area (in
frame pixels) and by the standard deviation of the window's intensities (floored at
``min_std``), so it is invariant to the window's scale, to intensity offsets (filters are zero
mean) and to contrast gain (Viola & Jones' variance normalisation).

**Any box, no resizing.** :func:`haar_features` maps each filter's corner points into a box of
any size (``x + px * w / W``) and reads the integral image there with bilinear interpolation.
Bilinear interpolation of an integral image is exactly the integral of the piecewise-constant
image over fractional rectangles, so a box that is an integer multiple of the window gives the
same values as the resized crop would with area averaging; at scale 1 it equals the dense path
:func:`haar_features_dense` used for training.

Intensities are expected on the 0..255 scale (uint8 or float); RGB is converted to luma.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from torchtrack.boxes import check_boxes
from torchtrack.errors import ConfigError, ShapeError, is_integer
from torchtrack.features.integral import check_pixel_values, integral_image, rgb_to_gray

__all__ = [
    "KINDS",
    "HaarBank",
    "HaarFeatures",
    "Integrals",
    "default_sizes",
    "haar_bank",
    "haar_features",
    "haar_features_at",
    "haar_features_dense",
    "integrals",
    "max_scales",
    "paper_pedestrian_count",
]

KINDS: tuple[str, ...] = ("edge_x", "edge_y", "diagonal", "line_x", "line_y")

# Each kind as weighted rectangles (y0, x0, y1, x1, weight) in units of the side T.
# line_x / line_y: centre minus the rest = 2 * centre - whole square (zero mean).
_RECTS: dict[str, list[tuple[float, float, float, float, float]]] = {
    "edge_x": [(0, 0, 1, 0.5, 1), (0, 0.5, 1, 1, -1)],
    "edge_y": [(0, 0, 0.5, 1, 1), (0.5, 0, 1, 1, -1)],
    "diagonal": [
        (0, 0, 0.5, 0.5, 1),
        (0, 0.5, 0.5, 1, -1),
        (0.5, 0, 1, 0.5, -1),
        (0.5, 0.5, 1, 1, 1),
    ],
    "line_x": [(0, 0.25, 1, 0.75, 2), (0, 0, 1, 1, -1)],
    "line_y": [(0.25, 0, 0.75, 1, 2), (0, 0, 1, 1, -1)],
}


def _corner_points(kind: str) -> list[tuple[float, float, float]]:
    """Integral-image corner points ``(fy, fx, coefficient)`` of one kind, duplicates merged."""
    pts: dict[tuple[float, float], float] = {}
    for y0, x0, y1, x1, w in _RECTS[kind]:
        for (py, px), s in (((y1, x1), 1), ((y0, x1), -1), ((y1, x0), -1), ((y0, x0), 1)):
            pts[(py, px)] = pts.get((py, px), 0.0) + s * w
    return [(py, px, c) for (py, px), c in sorted(pts.items()) if c != 0]


_POINTS = {k: _corner_points(k) for k in KINDS}
_MAX_POINTS = max(len(p) for p in _POINTS.values())  # 9 (diagonal)


def paper_pedestrian_count(window: tuple[int, int] = (128, 64)) -> int:
    """The paper's counting formula for the pedestrian bank: ``(H - T) * max(W - T, 1)`` positions
    per size (with ``H >= W``), times five. Gives 42,560 for 128 x 64; shown for comparison only."""
    h, w = window
    sizes = default_sizes(window, 3)
    return 5 * sum(max(h - t, 1) * max(w - t, 1) for t in sizes)


def max_scales(window: tuple[int, int]) -> int:
    """The most ``n_scales`` of a ``(H, W)`` window: its largest power of two and the halves of
    it down to 4 pixels (filter sides are multiples of 4)."""
    return max(int(min(window)).bit_length() - 2, 0)


def default_sizes(
    window: tuple[int, int], n_scales: int, *, key: str = "n_scales"
) -> tuple[int, ...]:
    """The paper's filter sides for a ``(H, W)`` window: the largest power of two not above
    ``min(H, W)`` and its ``n_scales - 1`` halves.

    Raises:
        ConfigError: ``n_scales`` not an integer in ``[1, max_scales(window)]`` (named ``key``).
    """
    most = max_scales(window)
    if isinstance(n_scales, bool) or not isinstance(n_scales, int) or not 1 <= n_scales <= most:
        # a huge n_scales built a list of that many sizes, then printed it in the error
        raise ConfigError(
            f"{key} must be an integer in [1, {most}] for a {window[0]}x{window[1]} window "
            f"(filter sides halve from the largest power of two that fits down to 4 pixels), "
            f"got {n_scales!r}"
        )
    t0 = 1 << (int(min(window)).bit_length() - 1)
    return tuple(t0 >> i for i in range(n_scales))


@dataclass(frozen=True)
class HaarBank:
    """A bank of Haar features for a training window of ``window = (H, W)`` pixels.

    Feature ``i`` is row ``i`` of :attr:`table` = ``(kind, size, y, x)``; rows are ordered by
    size (as given), then kind (as in :data:`KINDS`), then ``y``, then ``x``.

    Build it with :func:`haar_bank`; ``to_dict`` / ``from_dict`` give a JSON-safe form.
    """

    window: tuple[int, int]
    sizes: tuple[int, ...]
    stride: int = 1
    min_std: float = 1.0
    _table: torch.Tensor | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        h, w = self.window
        for name, v in (("window height", h), ("window width", w), ("stride", self.stride)):
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        if not self.sizes:
            raise ConfigError("sizes must name at least one filter size")
        for t in self.sizes:
            if not isinstance(t, int) or isinstance(t, bool) or t < 4 or t % 4:
                raise ConfigError(
                    f"filter sizes must be multiples of 4 (the line filters split the square "
                    f"in quarters), got {t!r} in sizes={list(self.sizes)}"
                )
            if t > min(h, w):
                raise ConfigError(
                    f"filter size {t} does not fit the {h}x{w} (HxW) window; use sizes <= {min(h, w)}"
                )
        if len(set(self.sizes)) != len(self.sizes):
            raise ConfigError(f"sizes must be distinct, got {list(self.sizes)}")
        if not (math.isfinite(self.min_std) and self.min_std > 0):
            raise ConfigError(f"min_std must be a positive number, got {self.min_std!r}")
        object.__setattr__(self, "_table", self._build_table())

    def _grid(self, t: int) -> tuple[int, int]:
        h, w = self.window
        return (h - t) // self.stride + 1, (w - t) // self.stride + 1

    def _build_table(self) -> torch.Tensor:
        rows = []
        for t in self.sizes:
            ny, nx = self._grid(t)
            ys = torch.arange(ny, dtype=torch.int64) * self.stride
            xs = torch.arange(nx, dtype=torch.int64) * self.stride
            gy, gx = torch.meshgrid(ys, xs, indexing="ij")
            for k in range(len(KINDS)):
                n = ny * nx
                rows.append(
                    torch.stack(
                        (
                            torch.full((n,), k, dtype=torch.int64),
                            torch.full((n,), t, dtype=torch.int64),
                            gy.reshape(-1),
                            gx.reshape(-1),
                        ),
                        1,
                    )
                )
        return torch.cat(rows)

    @property
    def table(self) -> torch.Tensor:
        """``(F, 4)`` int64: kind index, size, y, x (top-left in window pixels)."""
        return self._table  # type: ignore[return-value]  # set in __post_init__

    def __len__(self) -> int:
        return int(self.table.shape[0])

    def describe(self, i: int) -> dict[str, Any]:
        """Feature ``i`` as ``{"kind", "size", "y", "x"}``."""
        k, t, y, x = self.table[i].tolist()
        return {"kind": KINDS[k], "size": t, "y": y, "x": x}

    def integrals(self, frames: torch.Tensor) -> Integrals:
        """:class:`Integrals` of ``frames (B, C, H, W)`` (luma and its square)."""
        return integrals(frames)

    def crop_context(self, boxes: torch.Tensor) -> tuple[int, int]:
        """``(margin, alignment)`` in frame pixels that integral images computed over a crop
        need around ``boxes`` to give the full frame's values: none for luma sums."""
        return 0, 1

    def features_at(
        self,
        ints: Integrals,
        boxes: torch.Tensor,
        index: torch.Tensor | None = None,
        *,
        check: bool = True,
    ) -> torch.Tensor:
        """:func:`haar_features_at` with this bank."""
        return haar_features_at(ints, boxes, self, index, check=check)

    def to_dict(self) -> dict[str, Any]:
        return {
            "window": list(self.window),
            "sizes": list(self.sizes),
            "stride": self.stride,
            "min_std": self.min_std,
            "kinds": list(KINDS),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> HaarBank:
        """Inverse of :meth:`to_dict`; raises :class:`ConfigError` on unknown or missing keys."""
        if not isinstance(d, dict):
            raise ConfigError(f"a Haar bank description must be a mapping, got {type(d).__name__}")
        known = {"window", "sizes", "stride", "min_std", "kinds"}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(
                f"unknown Haar bank key(s): {sorted(unknown)}; known: {sorted(known)}"
            )
        missing = {"window", "sizes"} - set(d)
        if missing:
            raise ConfigError(f"Haar bank description lacks {sorted(missing)}")
        if "kinds" in d and list(d["kinds"]) != list(KINDS):
            raise ConfigError(
                f"Haar bank kinds {d['kinds']} differ from this version's {list(KINDS)}"
            )
        win = d["window"]
        if not isinstance(win, (list, tuple)) or len(win) != 2:
            raise ConfigError(f"window must be [H, W], got {win!r}")
        return cls(
            window=(win[0], win[1]),
            sizes=tuple(d["sizes"]),
            stride=d.get("stride", 1),
            min_std=float(d.get("min_std", 1.0)),
        )


def haar_bank(
    window: tuple[int, int],
    *,
    n_scales: int = 3,
    sizes: tuple[int, ...] | None = None,
    stride: int = 1,
    min_std: float = 1.0,
) -> HaarBank:
    """The paper's bank for a window of ``(H, W)`` pixels.

    Args:
        window: training window ``(H, W)``, e.g. ``(128, 64)`` for pedestrians.
        n_scales: number of sizes when ``sizes`` is not given: the largest power of two not
            above ``min(H, W)`` and its ``n_scales - 1`` halves (paper: 3).
        sizes: explicit filter sides (multiples of 4).
        stride: position step in window pixels (paper: 1).
        min_std: floor of the window standard deviation used for normalisation (intensity units).

    Example:
        >>> len(haar_bank((64, 64)))  # the paper's vehicle count
        17455
    """
    if sizes is None:
        sizes = default_sizes(window, n_scales)
    return HaarBank(window=tuple(window), sizes=tuple(sizes), stride=stride, min_std=min_std)


def _check_window_images(images: torch.Tensor, bank: HaarBank) -> torch.Tensor:
    if not isinstance(images, torch.Tensor) or images.ndim != 4:
        got = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ShapeError(f"crops must have shape (N, C, H, W), got {got}")
    if tuple(images.shape[-2:]) != tuple(bank.window):
        raise ShapeError(
            f"crops must be window-sized {bank.window[0]}x{bank.window[1]} (HxW), got "
            f"{images.shape[-2]}x{images.shape[-1]}; resize them or score them as boxes"
        )
    return rgb_to_gray(images)


def haar_features_dense(
    crops: torch.Tensor, bank: HaarBank, *, chunk: int = 512, out: torch.Tensor | None = None
) -> torch.Tensor:
    """Every feature of the bank on window-sized crops (the training path).

    Each corner point of a filter is a strided slice of the integral image, so one size and kind
    costs at most nine tensor additions for all positions and crops.

    Args:
        crops: ``(N, C, H, W)`` with ``(H, W) == bank.window``, C = 1 or 3, 0..255 intensities.
        bank: the feature bank.
        chunk: crops per step (bounds the float64 working memory to ~``chunk * F * 8`` bytes).
        out: optional preallocated ``(N, F)`` float32 result (e.g. a memory-mapped array).

    Returns:
        ``(N, F)`` float32 on the crops' device, columns in ``bank.table`` order.

    Raises:
        ShapeError: crops not ``(N, C, H, W)`` window-sized, or ``out`` not an ``(N, F)``
            floating-point tensor (an integer one truncated every feature, silently).
        ConfigError: ``chunk`` not an integer >= 1 (0 or less failed inside torch).
        DataError: a pixel not finite or outside [0, 255] (as for the box path: NaN crops
            gave NaN features, silently).
    """
    gray = _check_window_images(crops, bank)
    if not is_integer(chunk) or chunk < 1:
        raise ConfigError(f"chunk must be an integer >= 1 (crops per step), got {chunk!r}")
    chunk = int(chunk)
    check_pixel_values(crops, "crops")
    n = gray.shape[0]
    f = len(bank)
    if out is None:
        out = torch.empty((n, f), dtype=torch.float32, device=gray.device)
    elif (
        not isinstance(out, torch.Tensor)
        or tuple(out.shape) != (n, f)
        or not out.is_floating_point()
    ):
        got = (
            f"{tuple(out.shape)} {out.dtype}"
            if isinstance(out, torch.Tensor)
            else type(out).__name__
        )
        raise ShapeError(f"out must be a ({n}, {f}) floating-point tensor (float32), got {got}")
    h, w = bank.window
    s = bank.stride
    for start in range(0, n, chunk):
        g = gray[start : start + chunk]
        ii = integral_image(g)[:, 0]
        ii2 = integral_image(g, squared=True)[:, 0]
        area = float(h * w)
        mean = ii[:, h, w] / area
        var = (ii2[:, h, w] / area - mean * mean).clamp(min=0)
        std = var.sqrt().clamp(min=bank.min_std)  # (n,)
        col = 0
        for t in bank.sizes:
            ny, nx = bank._grid(t)
            for kind in KINDS:
                acc = torch.zeros((g.shape[0], ny, nx), dtype=ii.dtype, device=ii.device)
                for fy, fx, c in _POINTS[kind]:
                    py, px = round(fy * t), round(fx * t)
                    acc += c * ii[:, py : py + (ny - 1) * s + 1 : s, px : px + (nx - 1) * s + 1 : s]
                acc /= std[:, None, None] * float(t * t)
                out[start : start + g.shape[0], col : col + ny * nx] = acc.reshape(g.shape[0], -1)
                col += ny * nx
    return out


class Integrals(NamedTuple):
    """Integral images of a frame batch, computed once and shared by every box scored on it.

    ``ii`` and ``ii2``: ``(B, H + 1, W + 1)`` float64 sums of luma and of its square.
    """

    ii: torch.Tensor
    ii2: torch.Tensor

    @property
    def frame_size(self) -> tuple[int, int]:
        return int(self.ii.shape[-2]) - 1, int(self.ii.shape[-1]) - 1


def integrals(frames: torch.Tensor) -> Integrals:
    """``frames (B, C, H, W)`` (C = 1 or 3, 0..255) -> :class:`Integrals` of their luma.

    Both tables are accumulated together in float64 (one two-channel cumulative sum), which
    gives the same values as :func:`~torchtrack.features.integral.integral_image` of the luma
    and of its square: exact for integer (gray uint8) frames, and the same summation order
    for float luma.
    """
    gray = rgb_to_gray(frames)[:, 0].to(torch.float64)  # (B, H, W)
    check_pixel_values(frames)
    b, h, w = gray.shape
    both = torch.empty((b, 2, h + 1, w + 1), dtype=torch.float64, device=gray.device)
    both[:, :, 0, :] = 0
    both[:, :, :, 0] = 0
    inner = both[:, :, 1:, 1:]
    inner[:, 0] = gray
    torch.mul(gray, gray, out=inner[:, 1])
    inner.copy_(inner.cumsum(2).cumsum(3))
    return Integrals(both[:, 0], both[:, 1])


def _bilinear(ii: torch.Tensor, y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """Slow, obviously right reference of the bilinear reads :func:`haar_features_at` does with
    :func:`torch.nn.functional.grid_sample`: ``ii (B, H+1, W+1)`` at float coordinates
    ``y, x (B, M)``, clamped to the table (kept for the tests)."""
    b, hp, wp = ii.shape
    y = y.clamp(0, hp - 1)
    x = x.clamp(0, wp - 1)
    y0 = y.floor().clamp(max=hp - 2) if hp > 1 else y.floor()
    x0 = x.floor().clamp(max=wp - 2) if wp > 1 else x.floor()
    fy = y - y0
    fx = x - x0
    y0i = y0.long()
    x0i = x0.long()
    flat = ii.reshape(b, -1)
    i00 = y0i * wp + x0i
    v00 = flat.gather(1, i00)
    v01 = flat.gather(1, i00 + 1)
    v10 = flat.gather(1, i00 + wp)
    v11 = flat.gather(1, i00 + wp + 1)
    return (1 - fy) * ((1 - fx) * v00 + fx * v01) + fy * ((1 - fx) * v10 + fx * v11)


# Largest (points x features) coefficient matrix applied as one dense matrix product; larger
# selections (e.g. a whole bank) sum their corner values per group of features instead.
_DENSE_MAX = 1 << 20


class _PointTable(NamedTuple):
    """Corner points of selected features and how to combine them.

    ``basis``: ``(4, 2 (M + 4))`` float64; a box's ``(x0, sx, y0, sy)`` times it gives the
    interleaved ``(x0 + px sx, y0 + py sy)`` of the M corner points of its features followed by
    the box's own 4 corners (window points ``(H, W), (0, W), (H, 0), (0, 0)``).
    ``dense``: ``(M, K)`` float64 coefficients (point values @ dense = raw responses in index
    order) when ``M K <= _DENSE_MAX``, else ``None`` and ``groups`` are used:
    ``(n_features, n_points, coef (n_features, n_points))`` per group of features with the
    same number of points (6, 8, 9), contiguous in point order, and ``order`` ``(K,)`` puts
    the grouped responses back in index order. ``area``: ``(K,)`` float64 filter areas.
    """

    basis: torch.Tensor
    dense: torch.Tensor | None
    groups: tuple[tuple[int, int, torch.Tensor], ...]
    order: torch.Tensor
    area: torch.Tensor


_TABLE_CACHE: dict[tuple[Any, ...], _PointTable] = {}
_TABLE_CACHE_SIZE = 32


def _point_table(bank: HaarBank, index: torch.Tensor, device: torch.device) -> _PointTable:
    """The :class:`_PointTable` of ``bank`` rows ``index`` (int64, CPU), cached per bank, index,
    device and dense limit (a tracker scores the same few features on every frame)."""
    key = (bank, index.numpy().tobytes(), str(device), _DENSE_MAX)
    hit = _TABLE_CACHE.get(key)
    if hit is not None:
        return hit
    table = bank.table[index]  # (K, 4)
    k = table.shape[0]
    n_pts = torch.tensor([len(_POINTS[kind]) for kind in KINDS])[table[:, 0]]  # (K,)
    pts, groups, perm = [], [], []
    for p in sorted(set(n_pts.tolist())):
        sel = torch.nonzero(n_pts == p).flatten()
        rows = table[sel]
        ref = torch.stack(
            [torch.tensor(_POINTS[KINDS[i]], dtype=torch.float64) for i in rows[:, 0].tolist()]
        )  # (K_p, p, 3): fy, fx, coefficient
        t = rows[:, 1].to(torch.float64)[:, None]
        py = rows[:, 2].to(torch.float64)[:, None] + ref[..., 0] * t
        px = rows[:, 3].to(torch.float64)[:, None] + ref[..., 1] * t
        pts.append(torch.stack((py, px), -1).reshape(-1, 2))
        groups.append((int(sel.numel()), p, ref[..., 2].contiguous()))
        perm.append(sel)
    perm_t = torch.cat(perm)
    order = torch.empty(k, dtype=torch.int64)
    order[perm_t] = torch.arange(k)
    pts_t = torch.cat(pts)  # (M, 2) py, px
    m = pts_t.shape[0]
    wh, ww = (float(v) for v in bank.window)
    box = torch.tensor([[wh, ww], [0.0, ww], [wh, 0.0], [0.0, 0.0]], dtype=torch.float64)
    allp = torch.cat((pts_t, box))
    basis = torch.zeros((4, m + 4, 2), dtype=torch.float64)
    basis[0, :, 0] = 1.0
    basis[1, :, 0] = allp[:, 1]
    basis[2, :, 1] = 1.0
    basis[3, :, 1] = allp[:, 0]
    dense = None
    if m * k <= _DENSE_MAX:
        dense = torch.zeros((m, k), dtype=torch.float64)
        row = 0
        for (nf, p, coef), sel in zip(groups, perm, strict=True):
            cols = sel.repeat_interleave(p)
            dense[torch.arange(row, row + nf * p), cols] = coef.reshape(-1)
            row += nf * p
        dense = dense.to(device)
    out = _PointTable(
        basis.reshape(4, -1).to(device),
        dense,
        tuple((nf, p, coef.to(device)) for nf, p, coef in groups),
        order.to(device),
        (table[:, 1].to(torch.float64) ** 2).to(device),
    )
    if len(_TABLE_CACHE) >= _TABLE_CACHE_SIZE:
        _TABLE_CACHE.pop(next(iter(_TABLE_CACHE)))
    _TABLE_CACHE[key] = out
    return out


def _check_index(index: torch.Tensor | None, bank: HaarBank) -> torch.Tensor:
    if index is None:
        return torch.arange(len(bank))
    if not isinstance(index, torch.Tensor):
        index = torch.as_tensor(index)
    if index.ndim != 1 or index.dtype not in (torch.int32, torch.int64):
        raise ShapeError(
            f"index must be a 1-D integer tensor, got shape {tuple(index.shape)} {index.dtype}"
        )
    index = index.cpu().long()
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= len(bank)):
        raise ShapeError(
            f"feature index out of range [0, {len(bank)}): min {int(index.min())}, "
            f"max {int(index.max())}"
        )
    return index


def haar_features_at(
    ints: Integrals,
    boxes: torch.Tensor,
    bank: HaarBank,
    index: torch.Tensor | None = None,
    *,
    check: bool = True,
) -> torch.Tensor:
    """Selected features of ``bank`` in arbitrary boxes, read from precomputed integral images.

    Args:
        ints: :class:`Integrals` of B frames.
        boxes: ``(B, N, 4)`` x, y, w, h in frame pixels (see :mod:`torchtrack.boxes`); any size,
            aspect ratios other than the window's stretch the filters.
        bank: the feature bank (its window is mapped onto each box).
        index: ``(K,)`` feature indices into ``bank`` (default: all; costly for a full bank).
        check: validate boxes (finite, at least 1 pixel, overlapping the frame). Parts of a box
            outside the frame read as zero intensity; the normalising mean and standard
            deviation come from the visible part.

    Returns:
        ``(B, N, K)`` float32 on the integral images' device.

    Raises:
        ShapeError: wrong shapes or an out-of-range index.
        BoxError: a box is not finite, smaller than one pixel, or entirely outside the frame.
    """
    if not isinstance(boxes, torch.Tensor) or boxes.ndim != 3 or boxes.shape[-1] != 4:
        got = tuple(boxes.shape) if isinstance(boxes, torch.Tensor) else type(boxes).__name__
        raise ShapeError(f"boxes must have shape (B, N, 4), got {got}")
    b = ints.ii.shape[0]
    if boxes.shape[0] != b:
        raise ShapeError(f"boxes are for {boxes.shape[0]} frame(s) but {b} frame(s) were given")
    fh, fw = ints.frame_size
    if check:
        check_boxes(boxes, (fh, fw))
    idx = _check_index(index, bank)
    dev = ints.ii.device
    n = boxes.shape[1]
    k = idx.numel()
    if n == 0 or k == 0:
        return torch.zeros((b, n, k), dtype=torch.float32, device=dev)
    bx = boxes.to(device=dev, dtype=torch.float64)
    x, y, w, h = bx.unbind(-1)  # (B, N)
    sy = h / bank.window[0]
    sx = w / bank.window[1]
    tab = _point_table(bank, idx, dev)
    # Every corner point of every box (and the box's own corners) in grid_sample's normalised
    # coordinates, g = (origin + p * scale) * 2 / (size - 1) - 1, as one (B N, 4) @ (4, 2 M')
    # product whose rows come out in grid_sample's interleaved (x, y) layout.
    nx, ny = 2.0 / fw, 2.0 / fh  # the tables are (fh + 1) x (fw + 1)
    coeffs = torch.stack((x * nx - 1.0, sx * nx, y * ny - 1.0, sy * ny), -1)
    grid = (coeffs.reshape(b * n, 4) @ tab.basis).reshape(b, n, -1, 2)
    # Bilinear reads with coordinates clamped to the table ("border"): exactly the integral of
    # the zero-padded image over the fractional rectangles, and for the box corners the sums
    # over the box's visible part.
    ii = ints.ii.to(torch.float64)[:, None]
    vals = F.grid_sample(ii, grid, mode="bilinear", padding_mode="border", align_corners=True)
    vals = vals[:, 0]  # (B, N, M + 4)
    m = vals.shape[-1] - 4
    if tab.dense is not None:
        raw = vals[..., :m] @ tab.dense  # (B, N, K)
    else:
        parts, col = [], 0
        for n_feat, n_pts, coef in tab.groups:
            block = vals[..., col : col + n_feat * n_pts].reshape(b, n, n_feat, n_pts)
            parts.append((block * coef).sum(-1))
            col += n_feat * n_pts
        raw = torch.cat(parts, -1).index_select(-1, tab.order)
    ii2 = ints.ii2.to(torch.float64)[:, None]
    sq = F.grid_sample(
        ii2, grid[:, :, m:], mode="bilinear", padding_mode="border", align_corners=True
    )[:, 0]  # (B, N, 4)
    sgn = torch.tensor((1.0, -1.0, -1.0, 1.0), dtype=torch.float64, device=dev)
    s12 = torch.stack((vals[..., m:], sq), -2) @ sgn  # (B, N, 2): sums of luma and its square
    vis = (((x + w).clamp(0, fw) - x.clamp(0, fw)) * ((y + h).clamp(0, fh) - y.clamp(0, fh))).clamp(
        min=1e-12
    )
    mean = s12[..., 0] / vis
    std = (s12[..., 1] / vis - mean * mean).clamp(min=0).sqrt().clamp(min=bank.min_std)  # (B, N)
    feat = raw / (std * (sx * sy))[:, :, None] / tab.area
    return feat.to(torch.float32)


def haar_features(
    frames: torch.Tensor,
    boxes: torch.Tensor,
    bank: HaarBank,
    index: torch.Tensor | None = None,
    *,
    check: bool = True,
) -> torch.Tensor:
    """Selected Haar features of ``bank`` in boxes of any size on a batch of frames.

    Args:
        frames: ``(B, C, H, W)``, C = 1 or 3 (RGB), 0..255 intensities.
        boxes: ``(B, N, 4)`` x, y, w, h in frame pixels.
        bank, index, check: as in :func:`haar_features_at`.

    Returns:
        ``(B, N, K)`` float32.

    Example:
        >>> bank = haar_bank((16, 8), sizes=(8, 4))
        >>> frame = torch.randint(0, 256, (1, 1, 48, 64), dtype=torch.uint8)
        >>> haar_features(frame, torch.tensor([[[3.0, 5.0, 16.0, 32.0]]]), bank).shape
        torch.Size([1, 1, 370])
    """
    return haar_features_at(integrals(frames), boxes, bank, index, check=check)


class HaarFeatures(nn.Module):
    """Module wrapper of :func:`haar_features`; stores the bank and the feature index only."""

    def __init__(self, bank: HaarBank, index: torch.Tensor | None = None) -> None:
        super().__init__()
        self.bank = bank
        self.index = index

    def forward(self, frames: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """``frames (B, C, H, W)``, ``boxes (B, N, 4)`` -> ``(B, N, K)``."""
        return haar_features(frames, boxes, self.bank, self.index)
