"""Integral channel features (Dollár, Tu, Perona, Belongie, "Integral Channel Features", BMVC 2009).

**Channels** (:class:`ChannelSet`, computed by :func:`compute_channels`): colour (``L``, ``U``,
``V`` of CIE LUV, or ``gray`` luma), the gradient magnitude ``grad`` and ``orient``: the
gradient magnitude split into ``orientations`` unsigned orientation bins (linear interpolation
between the two nearest bins). Gradients are central differences (the values of kornia's
``spatial_gradient``, without its convolution) of L (colour sets) or of the luma (gray sets); the magnitude is normalised
by its local average (triangle filter of radius ``norm_radius``, plus ``norm_const``), as in
Dollár et al.'s ACF (PAMI 2014), which makes it invariant to local contrast. Values: L, gray in
[0, 1]; U, V about [-1.3, 1.8] (kornia's LUV / 100).

A **colour model on a grayscale image**: the gray image is taken as R = G = B, so L is its
lightness and U = V = 0 (neutral colour) - the model still runs; features over U and V then
carry no information and scores are lower than on colour footage of the same scene.

**Features** (:class:`ChannelBank`): weighted sums of rectangle means over one channel, with
rectangle corners on a lattice of ``cell`` x ``cell`` pixel cells of the detector window (ACF's
aggregation with ``shrink = cell``). Kinds: ``box`` (one rectangle: the first-order features of
Dollár et al. 2009, a single cell being ACF's feature) and the five Haar filters of Chateau et
al. (``edge_x``, ``edge_y``, ``diagonal``, ``line_x``, ``line_y``: differences of rectangle
means over any channel). A bank is drawn at random by :func:`channel_bank` (all single cells,
plus random boxes and random Haar filters, from a seed) and stored as tensors.

**Any box, few channel computations** ("The Fastest Pedestrian Detector in the West", Dollár,
Belongie, Perona, BMVC 2010). Channels are computed at octaves of the frame (level ``k``: the
frame averaged over ``2^k x 2^k`` blocks) and kept as integral images (:class:`ChannelIntegrals`,
levels computed on demand). A box of scale ``s`` (box size / window size) is read from the
nearest octave ``k = round(log2 s)`` (level 0 below scale 1), where it has scale
``r = s / 2^k``: every rectangle mean is an exact area integral of the level's channels over
the box's fractional rectangle (bilinear reads of the integral image), multiplied by
``r ** lambda`` (Dollár et al.'s power law, ``lambda`` = 0 for colour, ``gradient_lambda`` for
gradient channels). No image is resized per scale; one channel computation per octave serves
every box.

:func:`channel_features_at` reads features in any boxes (the scoring path); :func:`scale_lattice`
samples one scale's cell lattice over a whole frame so that every window on it is read with
integer offsets (the scanning path). Both give the same values for the same window.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from torchtrack.boxes import check_boxes
from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.integral import check_pixel_values

__all__ = [
    "CHANNEL_NAMES",
    "KINDS",
    "ChannelBank",
    "ChannelFeatures",
    "ChannelIntegrals",
    "ChannelSet",
    "Lattice",
    "box_levels",
    "channel_bank",
    "channel_features_at",
    "channel_integrals",
    "compute_channels",
    "scale_lattice",
    "window_features",
]

CHANNEL_NAMES: tuple[str, ...] = ("L", "U", "V", "gray", "grad", "orient")
KINDS: tuple[str, ...] = ("box", "edge_x", "edge_y", "diagonal", "line_x", "line_y")
_MAX_LEVEL = 6  # 64x downsampling: far beyond any window of a real frame
_MAX_FEATURES = 1_000_000


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


# ------------------------------------------------------------------------------- channels


def check_channel_values(
    names: Any,
    orientations: Any,
    norm_radius: Any,
    norm_const: Any,
    gradient_lambda: Any,
    *,
    prefix: str = "",
) -> tuple[str, ...]:
    """The checks of :class:`ChannelSet`; returns ``names`` as a tuple.

    Args:
        prefix: put before each value's name in the messages (a training config passes
            ``"features."``, so that the message names the key the user wrote).

    Raises:
        ConfigError: the first bad value, named.
    """
    key = f"{prefix}channels"
    if isinstance(names, str) or not isinstance(names, (list, tuple)) or not names:
        raise ConfigError(
            f"{key} must be a non-empty list of names from {list(CHANNEL_NAMES)}, got {names!r}"
        )
    where = f" in {key}" if prefix else ""
    for n in names:
        if n not in CHANNEL_NAMES:
            raise ConfigError(
                f"unknown channel name {n!r}{where}; valid channel names: "
                f"{', '.join(CHANNEL_NAMES)}"
            )
    if len(set(names)) != len(names):
        raise ConfigError(f"channel names{where} must be distinct, got {list(names)}")
    if not _is_int(orientations) or not 1 <= orientations <= 18:
        raise ConfigError(
            f"{prefix}orientations must be an integer in [1, 18], got {orientations!r}"
        )
    if not _is_int(norm_radius) or not 0 <= norm_radius <= 32:
        raise ConfigError(f"{prefix}norm_radius must be an integer in [0, 32], got {norm_radius!r}")
    if not _is_num(norm_const) or norm_const <= 0:
        raise ConfigError(f"{prefix}norm_const must be a positive number, got {norm_const!r}")
    if not _is_num(gradient_lambda) or not 0 <= gradient_lambda <= 2:
        raise ConfigError(
            f"{prefix}gradient_lambda must be a number in [0, 2], got {gradient_lambda!r}"
        )
    return tuple(names)


@dataclass(frozen=True)
class ChannelSet:
    """Which channels to compute, in order.

    Attributes:
        names: channel names from :data:`CHANNEL_NAMES`: ``L``, ``U``, ``V`` (CIE LUV),
            ``gray`` (BT.601 luma), ``grad`` (normalised gradient magnitude), ``orient``
            (``orientations`` oriented-gradient channels). Default: LUV + magnitude + 6
            orientations, Dollár et al.'s ten channels.
        orientations: number of unsigned orientation bins over [0, pi) for ``orient``.
        norm_radius: radius (pixels) of the triangle filter of the local gradient normalisation
            (0: off).
        norm_const: added to the local average before dividing (ACF: 0.005).
        gradient_lambda: power-law exponent of the gradient channels between scales (Dollár et
            al. 2010, 2014: about 0.1); colour channels use 0.

    Raises:
        ConfigError: an unknown or repeated channel name (the message lists the valid ones),
            or a value out of range.
    """

    names: tuple[str, ...] = ("L", "U", "V", "grad", "orient")
    orientations: int = 6
    norm_radius: int = 5
    norm_const: float = 0.005
    gradient_lambda: float = 0.1

    def __post_init__(self) -> None:
        names = check_channel_values(
            self.names, self.orientations, self.norm_radius, self.norm_const, self.gradient_lambda
        )
        object.__setattr__(self, "names", names)

    @property
    def colour(self) -> bool:
        """Whether LUV is computed (any of L, U, V)."""
        return any(n in self.names for n in ("L", "U", "V"))

    @property
    def channels(self) -> tuple[str, ...]:
        """The computed channels in order, ``orient`` expanded to ``orient0 .. orient{n-1}``."""
        out: list[str] = []
        for n in self.names:
            out += [f"orient{i}" for i in range(self.orientations)] if n == "orient" else [n]
        return tuple(out)

    def __len__(self) -> int:
        return len(self.channels)

    @property
    def lambdas(self) -> tuple[float, ...]:
        """Power-law exponent of every channel (0 for colour, ``gradient_lambda`` otherwise)."""
        return tuple(
            0.0 if c in ("L", "U", "V", "gray") else float(self.gradient_lambda)
            for c in self.channels
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "orientations": self.orientations,
            "norm_radius": self.norm_radius,
            "norm_const": self.norm_const,
            "gradient_lambda": self.gradient_lambda,
        }

    @classmethod
    def from_dict(cls, d: Any) -> ChannelSet:
        """Inverse of :meth:`to_dict`; every key is type- and range-checked.

        Raises:
            ConfigError: not a mapping, an unknown key, a missing ``names``, a wrong type or an
                out-of-range value (named).
        """
        if not isinstance(d, dict):
            raise ConfigError(f"a channel set must be a mapping, got {type(d).__name__}")
        known = {"names", "orientations", "norm_radius", "norm_const", "gradient_lambda"}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(
                f"unknown channel-set key(s) {sorted(unknown)}; known: {sorted(known)}"
            )
        if "names" not in d:
            raise ConfigError("a channel set needs 'names'")
        names = d["names"]
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise ConfigError(f"channel names must be a list of strings, got {names!r}")
        kw = {k: d[k] for k in known - {"names"} if k in d}
        if "norm_const" in kw and _is_int(kw["norm_const"]):
            kw["norm_const"] = float(kw["norm_const"])
        if "gradient_lambda" in kw and _is_int(kw["gradient_lambda"]):
            kw["gradient_lambda"] = float(kw["gradient_lambda"])
        return cls(names=tuple(names), **kw)


# sRGB -> linear RGB of every 8-bit value, computed once with kornia (exact for uint8 frames;
# kornia's elementwise version is most of the cost of its LUV conversion).
_LINEAR_LUT: dict[torch.device, torch.Tensor] = {}


def _linear_rgb(rgb: torch.Tensor) -> torch.Tensor:
    from kornia.color import rgb_to_linear_rgb

    if rgb.dtype == torch.uint8:
        lut = _LINEAR_LUT.get(rgb.device)
        if lut is None:
            v = torch.arange(256, dtype=torch.float32, device=rgb.device) / 255.0
            lut = rgb_to_linear_rgb(v.view(1, 1, 256).expand(3, 1, 256))[0, 0].contiguous()
            _LINEAR_LUT[rgb.device] = lut
        # index_select on the flat frame: the same values as lut[rgb.long()], 3x faster on CPU
        return lut.index_select(0, rgb.reshape(-1).long()).view(rgb.shape)
    return rgb_to_linear_rgb(rgb.float() / 255.0)


def _luv(rgb: torch.Tensor) -> torch.Tensor:
    """``(B, 3, H, W)`` RGB 0..255 -> CIE LUV ``(B, 3, H, W)`` float32 exactly as
    ``kornia.color.rgb_to_luv(rgb / 255)`` on the CPU (L in [0, 100]), with the sRGB
    linearisation of 8-bit input read from a 256-entry table."""
    lin = _linear_rgb(rgb)
    # kornia.color.rgb_to_xyz's CPU branch, on every device: its GPU branch is a cuDNN
    # convolution, which rounds its inputs to TF32 by default (10-bit mantissa: U, a difference
    # of near-equal terms, then differed from the CPU's by ~2e-3 relative on an H100); the
    # einsum runs as a matmul, which torch keeps in full float32 on CUDA
    k = torch.tensor(_XYZ, dtype=lin.dtype, device=lin.device)
    xyz = torch.einsum("oi, ...ihw -> ...ohw", k, lin)
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    # kornia.color.luv: CIE 1976 with the D65 white point, eps 1e-12 in the denominators
    thr = 0.008856
    lum = torch.where(y > thr, 116.0 * y.clamp(min=thr).pow(1.0 / 3.0) - 16.0, 903.3 * y)
    xw, yw, zw = 0.95047, 1.0, 1.08883
    uw = 4 * xw / (xw + 15 * yw + 3 * zw)
    vw = 9 * yw / (xw + 15 * yw + 3 * zw)
    den = x + 15 * y + 3 * z + 1e-12
    u = 13 * lum * (4 * x / den - uw)
    v = 13 * lum * (9 * y / den - vw)
    return torch.stack((lum, u, v), 1)


#: kornia.color.rgb_to_xyz's matrix (CIE RGB to XYZ, D65)
_XYZ = (
    (0.412453, 0.357580, 0.180423),
    (0.212671, 0.715160, 0.072169),
    (0.019334, 0.119193, 0.950227),
)


def _central_differences(x: torch.Tensor) -> torch.Tensor:
    """``(B, 1, H, W)`` -> ``(B, 1, 2, H, W)``: ``kornia.filters.spatial_gradient(x, "diff",
    normalized=False)`` (the difference of the two neighbours, borders replicated) in plain
    float32 arithmetic: the same values (a kernel of -1, 0, 1 rounds once, as one subtraction
    does), without a 3x3 convolution: on the CPU 10x faster, and on CUDA not rounded through
    TF32 (cuDNN's default for float32 convolutions)."""
    p = F.pad(x, (1, 1, 1, 1), mode="replicate")
    gx = p[..., 1:-1, 2:] - p[..., 1:-1, :-2]
    gy = p[..., 2:, 1:-1] - p[..., :-2, 1:-1]
    return torch.stack((gx, gy), 2)


def _box(x: torch.Tensor, k: int, dim: int) -> torch.Tensor:
    """Running mean of width ``k`` along ``dim`` (-1 or -2), valid part only (cumulative sums:
    the cost does not depend on ``k``)."""
    pad = (1, 0) if dim == -1 else (0, 0, 1, 0)
    c = F.pad(x, pad).cumsum(dim)
    n = c.shape[dim]
    return (c.narrow(dim, k, n - k) - c.narrow(dim, 0, n - k)) / k


def _triangle(x: torch.Tensor, r: int) -> torch.Tensor:
    """Triangle filter of radius ``r`` (weights 1, 2, .., r + 1, .., 1; ACF's ``convTri``) with
    a replicated border: two box filters of width ``r + 1`` per axis."""
    p = F.pad(x, (r, r, r, r), mode="replicate")
    k = r + 1
    return _box(_box(_box(_box(p, k, -1), k, -1), k, -2), k, -2)


def _check_frames(frames: Any) -> torch.Tensor:
    if not isinstance(frames, torch.Tensor) or frames.ndim != 4:
        got = tuple(frames.shape) if isinstance(frames, torch.Tensor) else type(frames).__name__
        raise ShapeError(f"frames must have shape (B, C, H, W), got {got}")
    if frames.shape[1] not in (1, 3):
        raise ShapeError(f"frames must have 1 (gray) or 3 (RGB) channels, got C={frames.shape[1]}")
    if frames.dtype == torch.bool or frames.is_complex():
        raise ShapeError(f"frames must be an integer or floating tensor, got {frames.dtype}")
    if frames.shape[-1] < 1 or frames.shape[-2] < 1:
        raise ShapeError(f"frames are empty: {tuple(frames.shape)}")
    return frames


#: OpenCV's most channels per image (``CV_CN_MAX``): :func:`_integral` interleaves up to this
#: many tables with ``cv2.merge``
_CV_MAX_CN = 512


def _channel_planes(x: torch.Tensor, cs: ChannelSet) -> list[torch.Tensor]:
    """The channels of checked frames ``x (B, 1 | 3, H, W)`` as planes ``(B, H, W)`` float32,
    in ``cs.channels`` order (views where a computation gives several at once)."""
    parts: dict[str, torch.Tensor] = {}
    if cs.colour:
        rgb = x if x.shape[1] == 3 else x.expand(-1, 3, -1, -1)
        luv = _luv(rgb) / 100.0
        parts.update(L=luv[:, 0:1], U=luv[:, 1:2], V=luv[:, 2:3])
    if "gray" in cs.names or not cs.colour:
        from torchtrack.features.integral import rgb_to_gray

        g = rgb_to_gray(x)
        parts["gray"] = (g if g.is_floating_point() else g.float()).float() / 255.0
    if "grad" in cs.names or "orient" in cs.names:
        src = parts["L"] if cs.colour else parts["gray"]
        d = _central_differences(src)
        gx, gy = d[:, :, 0], d[:, :, 1]  # (B, 1, H, W)
        mag = torch.sqrt(gx * gx + gy * gy)
        if cs.norm_radius > 0:
            mag = mag / (_triangle(mag, cs.norm_radius) + cs.norm_const)
        parts["grad"] = mag
        if "orient" in cs.names:
            n = cs.orientations
            o = torch.remainder(torch.atan2(gy, gx), math.pi) * (n / math.pi)  # [0, n)
            o0 = o.floor()
            frac = o - o0
            # bins in [0, n] (o reaches n by rounding): n wrapped to 0 in place, not by an
            # integer remainder (the same bins, several times faster)
            i0 = o0.long()
            i0.masked_fill_(i0 == n, 0)
            i1 = i0 + 1
            i1.masked_fill_(i1 == n, 0)
            hist = torch.zeros((x.shape[0], n, *mag.shape[-2:]), dtype=mag.dtype, device=mag.device)
            hist.scatter_add_(1, i0, mag * (1 - frac))
            hist.scatter_add_(1, i1, mag * frac)
            for i in range(n):
                parts[f"orient{i}"] = hist[:, i : i + 1]
    return [parts[c][:, 0] for c in cs.channels]


def compute_channels(
    frames: torch.Tensor,
    channels: ChannelSet | None = None,
    *,
    memory_format: torch.memory_format = torch.contiguous_format,
) -> torch.Tensor:
    """The channels of a batch of frames.

    Args:
        frames: ``(B, C, H, W)``, C = 1 (gray) or 3 (RGB), 0..255 (uint8 or float).
        channels: the channel set (default: :class:`ChannelSet` ``()``, ten channels).
        memory_format: ``torch.channels_last`` lays the result out as ``(B, H, W, C)`` in
            memory (the same values). The integral images do not need it: they are summed
            plane by plane (:class:`ChannelIntegrals`).

    Returns:
        ``(B, len(channels), H, W)`` float32 on the frames' device, in ``channels.channels``
        order.

    Raises:
        ShapeError: not ``(B, 1 | 3, H, W)``.
        DataError: a pixel not finite or outside [0, 255].
    """
    x = _check_frames(frames)
    check_pixel_values(x)
    planes = _channel_planes(x, channels or ChannelSet())
    if memory_format == torch.channels_last:
        return torch.stack(planes, -1).permute(0, 3, 1, 2)
    return torch.stack(planes, 1)


def _integral(planes: list[torch.Tensor]) -> torch.Tensor:
    """Channel planes ``(B, H, W)`` -> channels-last ``(B, H + 1, W + 1, C)`` float64
    summed-area tables (contiguous: the C values of one point are adjacent, which is how the
    lattices read them).

    On the CPU, OpenCV's ``cv2.integral`` of each plane (float64 accumulation, the same values
    as two float64 cumulative sums), interleaved by ``cv2.merge``: several times faster than
    torch's cumulative sums, and faster than one ``cv2.integral`` of the interleaved channels
    (1440x1080, ten channels: 27.5 against 37 ms, the same values).
    """
    first = planes[0]
    b, (h, w), c = first.shape[0], first.shape[-2:], len(planes)
    if first.device.type == "cpu" and c <= _CV_MAX_CN:
        import cv2

        tabs = [
            torch.from_numpy(
                cv2.merge(
                    [cv2.integral(p[i].contiguous().numpy(), sdepth=cv2.CV_64F) for p in planes]
                ).reshape(h + 1, w + 1, c)
            )
            for i in range(b)
        ]
        # cv2's own table, not a copy of it (a fresh 8-byte table costs page faults)
        return tabs[0][None] if b == 1 else torch.stack(tabs)
    out = torch.zeros((b, h + 1, w + 1, c), dtype=torch.float64, device=first.device)
    out[:, 1:, 1:] = torch.stack(planes, -1).to(torch.float64).cumsum(2).cumsum(1)
    return out


class ChannelIntegrals:
    """Channel integral images of a frame batch at octave levels, computed on demand.

    Level ``k`` is the frame averaged over ``2^k x 2^k`` blocks (pixels beyond the last whole
    block are dropped) and its channels' integral images, ``(B, H_k + 1, W_k + 1, C)`` float64
    (channels last) with ``H_k = H // 2^k``. One object serves every box scored on these frames.

    Args:
        frames: ``(B, 1 | 3, H, W)``, 0..255.
        channels: the channel set.
    """

    def __init__(self, frames: torch.Tensor, channels: ChannelSet) -> None:
        self.frames = _check_frames(frames)
        check_pixel_values(self.frames)
        self.channels = channels
        self._levels: dict[int, torch.Tensor] = {}

    @property
    def frame_size(self) -> tuple[int, int]:
        return int(self.frames.shape[-2]), int(self.frames.shape[-1])

    @property
    def batch(self) -> int:
        return int(self.frames.shape[0])

    @property
    def device(self) -> torch.device:
        return self.frames.device

    def max_level(self) -> int:
        """The deepest level with at least one whole block."""
        h, w = self.frame_size
        return max(0, min(_MAX_LEVEL, math.floor(math.log2(min(h, w)))))

    def level(self, k: int) -> torch.Tensor:
        """Integral images ``(B, H_k + 1, W_k + 1, C)`` of level ``k`` (computed once)."""
        k = min(int(k), self.max_level())
        tab = self._levels.get(k)
        if tab is None:
            f = self.frames if k == 0 else _block_means(self.frames, k)
            tab = _integral(_channel_planes(f, self.channels))
            self._levels[k] = tab
        return tab


def _block_means(frames: torch.Tensor, k: int) -> torch.Tensor:
    """``frames (B, C, H, W)`` averaged over ``2^k x 2^k`` blocks, float32 (pixels beyond the
    last whole block dropped): ``F.avg_pool2d(frames.float(), 2 ** k)``. Integer frames (8-bit
    video) are halved k times by sums of 2 x 2 blocks instead, which are exact in float32 as
    avg_pool2d's sums of integers are (the same values, bit for bit) and ~6x faster on the
    CPU (480 x 360 RGB: 0.24 against 1.55 ms)."""
    if frames.is_floating_point():
        return F.avg_pool2d(frames, 1 << k)
    f = frames.float()
    for _ in range(k):
        f = f[..., : f.shape[-2] // 2 * 2, : f.shape[-1] // 2 * 2]
        f = (
            f[..., 0::2, 0::2] + f[..., 0::2, 1::2] + f[..., 1::2, 0::2] + f[..., 1::2, 1::2]
        ) * 0.25
    return f


def channel_integrals(frames: torch.Tensor, channels: ChannelSet | None = None) -> ChannelIntegrals:
    """:class:`ChannelIntegrals` of ``frames (B, 1 | 3, H, W)`` (levels computed on demand)."""
    return ChannelIntegrals(frames, channels or ChannelSet())


def box_levels(scale: torch.Tensor, max_level: int) -> torch.Tensor:
    """Octave level of boxes of ``scale`` (box size / window size, any shape): the nearest
    octave, ``round(log2 s)``, clamped to ``[0, max_level]`` (level 0 below scale 1)."""
    k = torch.floor(torch.log2(scale.clamp_min(1e-12)) + 0.5)
    return k.clamp(0, max_level).to(torch.int64)


# ------------------------------------------------------------------------------- features


def _rects_of(
    kind: str, i0: int, j0: int, i1: int, j1: int
) -> list[tuple[int, int, int, int, int]]:
    """Weighted rectangles ``(i0, j0, i1, j1, weight)`` (cell units) of one feature."""
    if kind == "box":
        return [(i0, j0, i1, j1, 1)]
    im, jm = (i0 + i1) // 2, (j0 + j1) // 2
    if kind == "edge_x":
        return [(i0, j0, i1, jm, 1), (i0, jm, i1, j1, -1)]
    if kind == "edge_y":
        return [(i0, j0, im, j1, 1), (im, j0, i1, j1, -1)]
    if kind == "diagonal":
        return [
            (i0, j0, im, jm, 1),
            (i0, jm, im, j1, -1),
            (im, j0, i1, jm, -1),
            (im, jm, i1, j1, 1),
        ]
    q = (j1 - j0) // 4
    if kind == "line_x":
        return [(i0, j0 + q, i1, j1 - q, 1), (i0, j0, i1, j1, -1)]
    q = (i1 - i0) // 4
    return [(i0 + q, j0, i1 - q, j1, 1), (i0, j0, i1, j1, -1)]  # line_y


class _Points(NamedTuple):
    """Corner points of selected features, grouped by point count.

    ``groups``: per group ``(positions (K_g,), c, i, j (K_g, P_g) int64 lattice points,
    coef (K_g, P_g) float64)``; a feature's raw value is ``sum coef * lattice`` (a sum of
    rectangle *sums* divided by their areas in cells). ``lam (K,)`` float64: each feature's
    power-law exponent; ``lam_values`` its distinct values (sorted) and ``lam_index (K,)``
    which of them each feature has (``torch.unique(lam, return_inverse=True)``, computed once
    on the CPU: on a GPU each call would wait for the device).
    """

    groups: tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor], ...]
    lam: torch.Tensor
    lam_values: torch.Tensor
    lam_index: torch.Tensor


@dataclass(eq=False)
class ChannelBank:
    """Features over channels for a detector window of ``window = (H, W)`` pixels.

    Feature ``f`` is ``sum_r rects[f, r, 4] * mean(channel[f] over rects[f, r, :4])``, the
    rectangles ``(i0, j0, i1, j1)`` in cells of ``cell`` pixels (rows with weight 0 are unused).

    Attributes:
        window: ``(H, W)``, multiples of ``cell``.
        channels: the :class:`ChannelSet`.
        cell: lattice step in window pixels (ACF's shrink; default 4).
        rects: ``(F, 4, 5)`` int32.
        channel: ``(F,)`` int64 channel index into ``channels.channels``.

    Build a random candidate pool with :func:`channel_bank`; ``to_dict`` / ``from_dict``
    (JSON header + tensors) store it in a model file.

    Raises:
        ConfigError: invalid geometry or tables (named).
    """

    window: tuple[int, int]
    channels: ChannelSet
    rects: torch.Tensor
    channel: torch.Tensor
    cell: int = 4
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        _check_geometry(self.window, self.cell)
        if not isinstance(self.channels, ChannelSet):
            raise ConfigError(f"channels must be a ChannelSet, got {type(self.channels).__name__}")
        self.window = (int(self.window[0]), int(self.window[1]))
        r, c = self.rects, self.channel
        if not isinstance(r, torch.Tensor) or r.ndim != 3 or tuple(r.shape[1:]) != (4, 5):
            got = tuple(r.shape) if isinstance(r, torch.Tensor) else type(r).__name__
            raise ConfigError(f"rects must be a (F, 4, 5) integer tensor, got {got}")
        if r.dtype not in (torch.int16, torch.int32, torch.int64) or r.is_floating_point():
            raise ConfigError(f"rects must hold integers, got {r.dtype}")
        n = r.shape[0]
        if not 1 <= n <= _MAX_FEATURES:
            raise ConfigError(f"a channel bank needs 1..{_MAX_FEATURES} features, got {n}")
        if not isinstance(c, torch.Tensor) or tuple(c.shape) != (n,) or c.is_floating_point():
            raise ConfigError(f"channel must be a ({n},) integer tensor")
        r = r.to(torch.int32).cpu().contiguous()
        c = c.to(torch.int64).cpu().contiguous()
        hc, wc = self.window[0] // self.cell, self.window[1] // self.cell
        wgt = r[..., 4]
        used = wgt != 0
        i0, j0, i1, j1 = (r[..., k] for k in range(4))
        bad = used & ((i0 < 0) | (j0 < 0) | (i1 > hc) | (j1 > wc) | (i1 <= i0) | (j1 <= j0))
        if bool(bad.any()) or bool(((wgt < -4) | (wgt > 4)).any()):
            f = int(bad.any(1).nonzero()[0]) if bool(bad.any()) else -1
            raise ConfigError(
                f"feature rectangles must lie inside the {hc}x{wc}-cell window with weights in "
                f"[-4, 4] (first bad feature: {f})"
            )
        if not bool(used.any(1).all()):
            raise ConfigError("every feature needs at least one rectangle of non-zero weight")
        if int(c.min()) < 0 or int(c.max()) >= len(self.channels):
            raise ConfigError(
                f"feature channels must lie in [0, {len(self.channels)}) for channels "
                f"{list(self.channels.channels)}"
            )
        self.rects, self.channel = r, c

    @property
    def grid(self) -> tuple[int, int]:
        """``(H, W) // cell``: the window in cells."""
        return self.window[0] // self.cell, self.window[1] // self.cell

    def __len__(self) -> int:
        return int(self.rects.shape[0])

    def describe(self, i: int) -> dict[str, Any]:
        """Feature ``i`` as ``{"channel", "rects": [[i0, j0, i1, j1, weight], ...]}`` (cells)."""
        rows = [row for row in self.rects[i].tolist() if row[4] != 0]
        return {"channel": self.channels.channels[int(self.channel[i])], "rects": rows}

    def subset(self, index: torch.Tensor) -> ChannelBank:
        """A bank of features ``index`` only (in that order)."""
        idx = torch.as_tensor(index, dtype=torch.int64).cpu()
        return ChannelBank(
            self.window, self.channels, self.rects[idx], self.channel[idx], self.cell
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe description (the tables are tensors: :meth:`tensors`)."""
        return {
            "kind": "channels",
            "window": list(self.window),
            "cell": self.cell,
            "channels": self.channels.to_dict(),
            "n_features": len(self),
        }

    def tensors(self) -> dict[str, torch.Tensor]:
        return {"rects": self.rects.contiguous(), "channel": self.channel.contiguous()}

    @staticmethod
    def check_header(d: Any) -> tuple[ChannelSet, tuple[int, int], int, int]:
        """Validate a :meth:`to_dict` description before any table is read.

        Returns:
            ``(channels, window, cell, n_features)``.

        Raises:
            ConfigError: not a mapping, unknown or missing keys, wrong types or ranges (named).
        """
        if not isinstance(d, dict):
            raise ConfigError(
                f"a channel bank description must be a mapping, got {type(d).__name__}"
            )
        known = {"kind", "window", "cell", "channels", "n_features"}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(
                f"unknown channel bank key(s) {sorted(unknown)}; known: {sorted(known)}"
            )
        missing = known - set(d)
        if missing:
            raise ConfigError(f"channel bank description lacks {sorted(missing)}")
        if d["kind"] != "channels":
            raise ConfigError(f"channel bank kind must be 'channels', got {d['kind']!r}")
        cs = ChannelSet.from_dict(d["channels"])
        win, cell, n = d["window"], d["cell"], d["n_features"]
        if not isinstance(win, list) or len(win) != 2 or not all(_is_int(v) for v in win):
            raise ConfigError(f"window must be [H, W] integers, got {win!r}")
        if not _is_int(cell):
            raise ConfigError(f"cell must be an integer, got {cell!r}")
        _check_geometry((win[0], win[1]), cell)
        if not _is_int(n) or not 1 <= n <= _MAX_FEATURES:
            raise ConfigError(f"n_features must be an integer in [1, {_MAX_FEATURES}], got {n!r}")
        return cs, (win[0], win[1]), cell, n

    @classmethod
    def from_dict(cls, d: Any, tensors: dict[str, torch.Tensor]) -> ChannelBank:
        """Inverse of :meth:`to_dict` + :meth:`tensors` (every field validated)."""
        cs, window, cell, n = cls.check_header(d)
        for key, shape in (("rects", (n, 4, 5)), ("channel", (n,))):
            t = tensors.get(key)
            if not isinstance(t, torch.Tensor) or tuple(t.shape) != shape:
                got = tuple(t.shape) if isinstance(t, torch.Tensor) else None
                raise ConfigError(f"channel bank tensor {key!r} must have shape {shape}, got {got}")
        return cls(window, cs, tensors["rects"], tensors["channel"], cell)

    # -- evaluation tables
    def points(self, index: torch.Tensor | None, device: torch.device) -> _Points:
        """Corner points of features ``index`` (default all), cached per index and device."""
        idx = torch.arange(len(self)) if index is None else _check_index(index, len(self))
        key = (idx.numpy().tobytes(), str(device))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        r = self.rects[idx].to(torch.int64)  # (K, 4, 5)
        k = r.shape[0]
        i0, j0, i1, j1, w = (r[..., q] for q in range(5))
        area = ((i1 - i0) * (j1 - j0)).clamp_min(1).to(torch.float64)
        wa = w.to(torch.float64) / area  # (K, 4)
        ci = torch.stack((i1, i0, i1, i0), -1)  # corners: (i1, j1) + (i0, j1) - (i1, j0) - ...
        cj = torch.stack((j1, j1, j0, j0), -1)
        cs = torch.tensor((1.0, -1.0, -1.0, 1.0), dtype=torch.float64)
        coef = (wa[..., None] * cs).reshape(k, 16)
        ci, cj = ci.reshape(k, 16), cj.reshape(k, 16)
        # merge duplicate corners of one feature (Haar filters share corners)
        hc, wc = self.grid
        stride = (hc + 1) * (wc + 1)
        key_f = torch.arange(k)[:, None] * stride + ci * (wc + 1) + cj
        keys, inv = torch.unique(key_f.reshape(-1), return_inverse=True)
        merged = torch.zeros(keys.numel(), dtype=torch.float64).index_add_(0, inv, coef.reshape(-1))
        keep = merged.abs() > 1e-12
        keys, merged = keys[keep], merged[keep]
        feat = keys // stride
        pij = keys % stride
        counts = torch.bincount(feat, minlength=k)
        start = torch.cumsum(counts, 0) - counts
        pos = torch.arange(keys.numel()) - start[feat]
        chan = self.channel[idx]
        groups = []
        for p in sorted(set(counts.tolist())):
            sel = torch.nonzero(counts == p).flatten()
            rows = torch.isin(feat, sel)
            fi = feat[rows]
            order = torch.searchsorted(sel, fi)
            gi = torch.zeros((sel.numel(), p), dtype=torch.int64)
            gj = torch.zeros_like(gi)
            gc = torch.zeros((sel.numel(), p), dtype=torch.float64)
            gi[order, pos[rows]] = pij[rows] // (wc + 1)
            gj[order, pos[rows]] = pij[rows] % (wc + 1)
            gc[order, pos[rows]] = merged[rows]
            gch = chan[sel][:, None].expand(-1, p).contiguous()
            groups.append(tuple(t.to(device) for t in (sel, gch, gi, gj, gc)))
        lam = torch.tensor(self.channels.lambdas, dtype=torch.float64)[chan]
        lam_u, lam_inv = torch.unique(lam, return_inverse=True)
        out = _Points(tuple(groups), lam.to(device), lam_u.to(device), lam_inv.to(device))
        if len(self._cache) > 32:
            self._cache.pop(next(iter(self._cache)))
        self._cache[key] = out
        return out

    def padded_points(
        self, index: torch.Tensor | None, device: torch.device
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(c, i, j, coef, lam)``: the corner points of features ``index`` in index order,
        padded to the largest count (``(K, P)``; padding has coefficient 0), and their
        power-law exponents ``(K,)`` (the scanning path)."""
        pts = self.points(index, device)
        k = sum(int(g[0].numel()) for g in pts.groups)
        p = max(int(g[2].shape[1]) for g in pts.groups)
        c = torch.zeros((k, p), dtype=torch.int64, device=device)
        i, j = torch.zeros_like(c), torch.zeros_like(c)
        coef = torch.zeros((k, p), dtype=torch.float64, device=device)
        for sel, gc, gi, gj, gco in pts.groups:
            q = gi.shape[1]
            c[sel, :q], i[sel, :q], j[sel, :q], coef[sel, :q] = gc, gi, gj, gco
        return c, i, j, coef, pts.lam

    def crop_context(self, boxes: torch.Tensor) -> tuple[int, int]:
        """``(margin, alignment)`` in frame pixels that channels computed over a crop need
        around ``boxes (..., 4)`` to equal the full frame's inside the boxes: the gradient and
        normalisation radius at the deepest octave the boxes use, and that octave's block size
        (the crop's origin must lie on the block grid)."""
        if boxes.numel() == 0:
            return 0, 1
        wh, ww = self.window
        s = torch.sqrt((boxes[..., 2] / ww) * (boxes[..., 3] / wh)).clamp_min(1e-12)
        k = int(box_levels(s, _MAX_LEVEL).max())
        return (self.channels.norm_radius + 2) << k, 1 << k

    def integrals(self, frames: torch.Tensor) -> ChannelIntegrals:
        """:class:`ChannelIntegrals` of ``frames`` for this bank's channels."""
        return ChannelIntegrals(frames, self.channels)

    def features_at(
        self,
        ints: ChannelIntegrals,
        boxes: torch.Tensor,
        index: torch.Tensor | None = None,
        *,
        check: bool = True,
    ) -> torch.Tensor:
        """:func:`channel_features_at` with this bank."""
        return channel_features_at(ints, boxes, self, index, check=check)


def _check_geometry(window: Any, cell: Any, cell_key: str = "cell") -> None:
    """``cell_key``: the cell's name in the messages (a training config's ``features.cell``)."""
    if not isinstance(window, (list, tuple)) or len(window) != 2:
        raise ConfigError(f"window must be (H, W), got {window!r}")
    if not _is_int(cell) or not 1 <= cell <= 64:
        raise ConfigError(f"{cell_key} must be an integer in [1, 64], got {cell!r}")
    size = "the cell size" if cell_key == "cell" else cell_key
    for v in window:
        if not _is_int(v) or v < cell or v % cell or v > 4096:
            raise ConfigError(
                f"window {list(window)} must be positive multiples of {size} {cell} "
                "(at most 4096 pixels)"
            )


def _check_index(index: Any, n: int) -> torch.Tensor:
    if not isinstance(index, torch.Tensor):
        index = torch.as_tensor(index)
    if index.ndim != 1 or index.dtype not in (torch.int32, torch.int64):
        raise ShapeError(
            f"index must be a 1-D integer tensor, got shape {tuple(index.shape)} {index.dtype}"
        )
    index = index.cpu().long()
    if index.numel() and (int(index.min()) < 0 or int(index.max()) >= n):
        raise ShapeError(
            f"feature index out of range [0, {n}): min {int(index.min())}, max {int(index.max())}"
        )
    return index


def channel_bank(
    window: tuple[int, int],
    channels: ChannelSet | None = None,
    *,
    cell: int = 4,
    cells: bool = True,
    boxes: int = 4000,
    haar: int = 4000,
    seed: int = 0,
) -> ChannelBank:
    """A random candidate pool of channel features for a window of ``(H, W)`` pixels.

    Args:
        window: ``(H, W)``, multiples of ``cell``.
        channels: the channel set (default: LUV + magnitude + 6 orientations).
        cell: lattice step in pixels.
        cells: include every single cell of every channel (ACF's features).
        boxes: random rectangles per bank (first-order features of Dollár et al. 2009; two
            distinct lattice rows and columns drawn uniformly).
        haar: random Chateau Haar filters (kind, channel, size and position uniform among those
            that split evenly into cells).
        seed: the random draw (the pool is reproducible).

    Raises:
        ConfigError: bad geometry or counts.
    """
    cs = channels or ChannelSet()
    _check_geometry(window, cell)
    for name, v in (("boxes", boxes), ("haar", haar)):
        if not _is_int(v) or v < 0:
            raise ConfigError(f"{name} must be a non-negative integer, got {v!r}")
    hc, wc = window[0] // cell, window[1] // cell
    nch = len(cs)
    g = torch.Generator().manual_seed(int(seed))
    rows: list[list[tuple[int, int, int, int, int]]] = []
    chans: list[int] = []
    if cells:
        for c in range(nch):
            for i in range(hc):
                for j in range(wc):
                    rows.append([(i, j, i + 1, j + 1, 1)])
                    chans.append(c)
    for _ in range(boxes):
        i0, i1 = sorted(torch.randperm(hc + 1, generator=g)[:2].tolist())
        j0, j1 = sorted(torch.randperm(wc + 1, generator=g)[:2].tolist())
        rows.append(_rects_of("box", i0, j0, i1, j1))
        chans.append(int(torch.randint(nch, (1,), generator=g)))
    kinds = [k for k in KINDS[1:]]
    steps = {
        "edge_x": (1, 2),
        "edge_y": (2, 1),
        "diagonal": (2, 2),
        "line_x": (1, 4),
        "line_y": (4, 1),
    }
    n_haar = 0
    while n_haar < haar:
        kind = kinds[int(torch.randint(len(kinds), (1,), generator=g))]
        si, sj = steps[kind]
        if hc < si or wc < sj:
            if all(hc < steps[k][0] or wc < steps[k][1] for k in kinds):
                break  # no Haar filter fits this window
            continue
        h = si * int(torch.randint(1, hc // si + 1, (1,), generator=g))
        w = sj * int(torch.randint(1, wc // sj + 1, (1,), generator=g))
        i0 = int(torch.randint(hc - h + 1, (1,), generator=g))
        j0 = int(torch.randint(wc - w + 1, (1,), generator=g))
        rows.append(_rects_of(kind, i0, j0, i0 + h, j0 + w))
        chans.append(int(torch.randint(nch, (1,), generator=g)))
        n_haar += 1
    if not rows:
        raise ConfigError(
            "the channel bank is empty: enable cells or ask for boxes / haar features"
        )
    table = torch.zeros((len(rows), 4, 5), dtype=torch.int32)
    for f, rs in enumerate(rows):
        table[f, : len(rs)] = torch.tensor(rs, dtype=torch.int32)
    return ChannelBank((int(window[0]), int(window[1])), cs, table, torch.tensor(chans), cell)


def _combine(
    vals: torch.Tensor,
    pts: _Points,
    k: int,
    lattice_w: int,
    lattice_hw: int,
    norm: torch.Tensor,
    logr: torch.Tensor,
) -> torch.Tensor:
    """Features ``(..., K)`` from per-box window lattices ``vals (..., C * Lh * Lw)``."""
    out = torch.empty((*vals.shape[:-1], k), dtype=torch.float64, device=vals.device)
    for sel, gc, gi, gj, coef in pts.groups:
        flat = (gc * lattice_hw + gi * lattice_w + gj).reshape(-1)
        v = vals.index_select(-1, flat).reshape(*vals.shape[:-1], *gi.shape)
        out[..., sel] = (v * coef).sum(-1)
    power = torch.exp(logr[..., None] * pts.lam)  # r ** lambda per box and feature
    return out * (norm[..., None] * power)


#: boxes per block in :func:`channel_features_at` (bounds its lattice workspace)
_BOX_CHUNK = 256


def channel_features_at(
    ints: ChannelIntegrals,
    boxes: torch.Tensor,
    bank: ChannelBank,
    index: torch.Tensor | None = None,
    *,
    check: bool = True,
) -> torch.Tensor:
    """Features ``index`` of ``bank`` in boxes of any size, read from channel integral images.

    Each box is read at its octave level (:func:`box_levels`): its cell lattice is sampled from
    the level's integral images with bilinear reads (exact area integrals over fractional
    rectangles) and every feature combines those lattice values. Parts of a box outside the
    frame read as zero-valued channels (the means still divide by the whole rectangle).

    Args:
        ints: :class:`ChannelIntegrals` of B frames (the bank's channels).
        boxes: ``(B, N, 4)`` x, y, w, h in frame pixels; an aspect ratio other than the
            window's stretches the lattice.
        bank: the features.
        index: ``(K,)`` features of ``bank`` (default all).
        check: validate boxes (finite, at least a pixel, overlapping the frame).

    Returns:
        ``(B, N, K)`` float32.

    Raises:
        ShapeError: wrong shapes, an out-of-range index or integrals of another channel set.
        BoxError: an invalid box (with ``check``).
    """
    if not isinstance(boxes, torch.Tensor) or boxes.ndim != 3 or boxes.shape[-1] != 4:
        got = tuple(boxes.shape) if isinstance(boxes, torch.Tensor) else type(boxes).__name__
        raise ShapeError(f"boxes must have shape (B, N, 4), got {got}")
    if not isinstance(ints, ChannelIntegrals):
        raise ShapeError(f"channel features need ChannelIntegrals, got {type(ints).__name__}")
    if ints.channels != bank.channels:
        raise ShapeError(
            f"integrals of channels {ints.channels.channels} given to a bank of "
            f"{bank.channels.channels}"
        )
    b = ints.batch
    if boxes.shape[0] != b:
        raise ShapeError(f"boxes are for {boxes.shape[0]} frame(s) but {b} frame(s) were given")
    fh, fw = ints.frame_size
    if check:
        check_boxes(boxes, (fh, fw))
    dev = ints.device
    pts = bank.points(index, dev)
    k = sum(int(g[0].numel()) for g in pts.groups)
    n = boxes.shape[1]
    if n == 0 or k == 0:
        return torch.zeros((b, n, k), dtype=torch.float32, device=dev)
    bx = boxes.to(device=dev, dtype=torch.float64)
    x, y, w, h = bx.unbind(-1)
    wh, ww = bank.window
    sx, sy = w / ww, h / wh
    scale = torch.sqrt(sx * sy)
    levels = box_levels(scale, ints.max_level())
    hc, wc = bank.grid
    lh, lw = hc + 1, wc + 1
    cell = float(bank.cell)
    li = torch.arange(lh, dtype=torch.float64, device=dev) * cell
    lj = torch.arange(lw, dtype=torch.float64, device=dev) * cell
    out = torch.empty((b, n, k), dtype=torch.float32, device=dev)
    compact = _compact_lattice(pts, k, lw, lh * lw, len(bank.channels.channels), dev)
    if compact is not None:  # the lattice points each channel reads, channel by channel
        pos, rows, _ = compact
        nch, npos = pos.shape
        used = pos.reshape(-1).index_select(0, rows)  # (R,) lattice positions, channel-major
        counts = torch.bincount(rows // npos, minlength=nch).tolist()
    present = torch.unique(levels).tolist()
    for lev in present:
        if len(present) == 1:
            groups = [(slice(None), slice(None))]
        else:  # boxes of this level only, frame by frame (the frame loop is short)
            groups = []
            for fi in range(b):
                sel = torch.nonzero(levels[fi] == lev).flatten()
                if sel.numel():
                    groups.append((slice(fi, fi + 1), sel))
        tab_all = ints.level(lev).permute(0, 3, 1, 2)  # (B, C, Hk + 1, Wk + 1) view
        hk, wk = tab_all.shape[-2] - 1, tab_all.shape[-1] - 1
        f = float(1 << lev)
        # At most _BOX_CHUNK boxes at a time: the lattice workspace (C Lh Lw values per box,
        # float64) stays a few MB however many windows are scored.
        chunks = []
        for fs, sel in groups:
            m = n if isinstance(sel, slice) else int(sel.numel())
            for s0 in range(0, m, _BOX_CHUNK):
                part = slice(s0, s0 + _BOX_CHUNK)
                chunks.append((fs, part if isinstance(sel, slice) else sel[part]))
        for fs, sel in chunks:
            tab = tab_all[fs]
            xs, ys, sxs, sys_ = x[fs][:, sel], y[fs][:, sel], sx[fs][:, sel], sy[fs][:, sel]
            bb, nn = xs.shape
            # lattice point (i, j) of a box: (x + j cell sx, y + i cell sy) frame pixels, / 2^k
            gx = ((xs[..., None] + sxs[..., None] * lj) / f) * (2.0 / max(wk, 1)) - 1.0
            gy = ((ys[..., None] + sys_[..., None] * li) / f) * (2.0 / max(hk, 1)) - 1.0
            # Grid coordinates of every lattice point of every box, ordered (i, j, box), the
            # box axis innermost.
            full = torch.stack(
                (
                    gx.transpose(1, 2)[:, None, :, :].expand(bb, lh, lw, nn),
                    gy.transpose(1, 2)[:, :, None, :].expand(bb, lh, lw, nn),
                ),
                -1,
            ).view(bb, lh * lw, nn, 2)
            if compact is None:
                # grid_sample's output (bb, C, Lh Lw nn) is then the lattice-major (bb, C Lh Lw,
                # nn) with no copy, and every corner read of _combine_lattice_major is a
                # contiguous row of nn values.
                vals = F.grid_sample(
                    tab,
                    full.view(bb, lh * lw * nn, 1, 2),
                    mode="bilinear",
                    padding_mode="border",
                    align_corners=True,
                )
                vals = vals.view(bb, -1, nn)  # (bb, C Lh Lw, nn)
            else:
                # Only the lattice values the features read: each channel's plane (of the
                # channels-last table, no copy) is sampled at that channel's own positions, in
                # the order of the used values (channel-major, then position), so no value is
                # sampled twice or thrown away; the same coordinates give the same bilinear
                # values as the whole lattice's read.
                vals = []
                for i in range(bb):
                    g = full[i].index_select(0, used)  # (R, nn, 2)
                    parts, r0 = [], 0
                    for c, cnt in enumerate(counts):
                        if cnt:
                            parts.append(
                                F.grid_sample(
                                    tab[i, c][None, None],
                                    g[r0 : r0 + cnt].view(1, cnt * nn, 1, 2),
                                    mode="bilinear",
                                    padding_mode="border",
                                    align_corners=True,
                                ).view(cnt, nn)
                            )
                            r0 += cnt
                    vals.append(torch.cat(parts))
                vals = vals[0].unsqueeze(0) if bb == 1 else torch.stack(vals)  # (bb, R, nn)
            rx, ry = sxs / f, sys_ / f
            norm = 1.0 / (cell * cell * rx * ry)
            logr = 0.5 * torch.log(rx * ry)
            feats = _combine_lattice_major(
                vals, pts, k, lw, lh * lw, norm, logr, None if compact is None else compact[2]
            )
            feats = feats.to(torch.float32)
            if isinstance(sel, slice):
                out[fs, sel] = feats
            else:
                out[fs.start, sel] = feats[0]
    return out.to(torch.float32)


_SPARSE: dict[tuple[int, int, int, int, str], tuple[_Points, torch.Tensor]] = {}


def _combination_matrix(
    pts: _Points,
    k: int,
    lattice_w: int,
    lattice_hw: int,
    n_cols: int,
    device: torch.device,
    colmap: torch.Tensor | None = None,
) -> torch.Tensor:
    """``(K, n_cols)`` float64 CSR matrix of :class:`_Points` coefficients: row = feature,
    column = the lattice row ``c Lh Lw + i Lw + j`` of each point, or ``colmap`` of it."""
    rows, cols, coefs = [], [], []
    for sel, gc, gi, gj, coef in pts.groups:
        flat = (gc * lattice_hw + gi * lattice_w + gj).reshape(-1)  # (K_g P_g,)
        rows.append(sel[:, None].expand(-1, gc.shape[1]).reshape(-1))
        cols.append(flat if colmap is None else colmap.to(flat.device)[flat])
        coefs.append(coef.reshape(-1))
    idx = torch.stack((torch.cat(rows), torch.cat(cols)))
    with warnings.catch_warnings():  # "sparse CSR support is in beta state"
        warnings.simplefilter("ignore", UserWarning)
        coo = torch.sparse_coo_tensor(
            idx, torch.cat(coefs), (k, n_cols), check_invariants=True
        ).coalesce()
        return coo.to_sparse_csr().to(device)


def _sparse_combination(
    pts: _Points, k: int, lattice_w: int, lattice_hw: int, n_lat: int, device: torch.device
) -> torch.Tensor:
    """``(K, n_lat)`` float64 CSR matrix of :class:`_Points` coefficients (row = feature,
    columns ascending = the points' order), cached per point table and lattice."""
    key = (id(pts), lattice_w, lattice_hw, n_lat, str(device))
    hit = _SPARSE.get(key)
    if hit is not None and hit[0] is pts:  # a new table may reuse a dead one's id
        return hit[1]
    w = _combination_matrix(pts, k, lattice_w, lattice_hw, n_lat, device)
    if len(_SPARSE) >= 32:
        _SPARSE.pop(next(iter(_SPARSE)))
    _SPARSE[key] = (pts, w)
    return w


_COMPACT: dict[tuple[int, int, int, int, str], tuple[_Points, Any]] = {}

#: read only the lattice points the features use when they are at most this share of the
#: lattice (a detector's tracking head reads ~700 of a window's 5,610 channel lattice values)
_COMPACT_SHARE = 0.5


def _compact_lattice(
    pts: _Points, k: int, lattice_w: int, lattice_hw: int, n_ch: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    """The lattice points the features of ``pts`` read, channel by channel, or ``None`` when
    they are more than :data:`_COMPACT_SHARE` of the ``n_ch x lattice_hw`` lattice values.

    Returns ``(pos (C, P), rows (R,), w)``: ``pos[c]`` the lattice positions (``i * Lw + j``,
    increasing; padded with position 0) channel ``c`` is sampled at, ``rows`` where the ``R``
    used values (channel-major, then position: the order of the whole lattice's rows) lie in
    the ``C x P`` samples, and ``w`` the ``(K, R)`` CSR combination matrix: the matrix of
    :func:`_sparse_combination` with its unused columns left out (the same entries in the same
    order, so the same sums)."""
    key = (id(pts), lattice_w, lattice_hw, n_ch, str(device))
    hit = _COMPACT.get(key)
    if hit is not None and hit[0] is pts:
        return hit[1]
    flat = torch.cat(
        [
            (gc * lattice_hw + gi * lattice_w + gj).reshape(-1).cpu()
            for _, gc, gi, gj, _ in pts.groups
        ]
    )
    used = torch.unique(flat)  # sorted
    out = None
    if used.numel() <= _COMPACT_SHARE * n_ch * lattice_hw:
        ch, pos = used // lattice_hw, used % lattice_hw
        counts = torch.bincount(ch, minlength=n_ch)
        rank = torch.arange(used.numel()) - (torch.cumsum(counts, 0) - counts)[ch]
        p_max = int(counts.max())
        pos_pad = torch.zeros((n_ch, p_max), dtype=torch.int64)
        pos_pad[ch, rank] = pos
        colmap = torch.full((n_ch * lattice_hw,), -1, dtype=torch.int64)
        colmap[used] = torch.arange(used.numel())
        w = _combination_matrix(pts, k, lattice_w, lattice_hw, used.numel(), device, colmap)
        out = (pos_pad.to(device), (ch * p_max + rank).to(device), w)
    if len(_COMPACT) >= 32:
        _COMPACT.pop(next(iter(_COMPACT)))
    _COMPACT[key] = (pts, out)
    return out


def _combine_lattice_major(
    vals: torch.Tensor,
    pts: _Points,
    k: int,
    lattice_w: int,
    lattice_hw: int,
    norm: torch.Tensor,
    logr: torch.Tensor,
    w: torch.Tensor | None = None,
) -> torch.Tensor:
    """:func:`_combine` of lattices stored lattice-major, ``vals (B, C * Lh * Lw, N)`` (or the
    used rows only, ``vals (B, R, N)`` with ``w`` from :func:`_compact_lattice`): the
    features are one sparse ``(K, C Lh Lw)`` matrix (a feature's few corner coefficients,
    in the points' order) times the lattice values, every read a whole row of N boxes.
    Returns ``(B, N, K)`` float64 (a transposed view)."""
    b, n_lat, _ = vals.shape
    if w is None:
        w = _sparse_combination(pts, k, lattice_w, lattice_hw, n_lat, vals.device)
    out = torch.stack([w @ vals[i] for i in range(b)])  # (B, K, N)
    # r ** lambda per box and feature: lambda takes a few values (one per channel type), so
    # exponentiate each once per box and spread (the same products, the same exp inputs).
    power = torch.exp(pts.lam_values[:, None] * logr[:, None, :]).index_select(1, pts.lam_index)
    return (out * (norm[:, None, :] * power)).transpose(1, 2)


def window_features(
    crops: torch.Tensor,
    bank: ChannelBank,
    region: tuple[int, int, int, int] | None = None,
    index: torch.Tensor | None = None,
) -> torch.Tensor:
    """Features of the same window ``region = (x, y, w, h)`` (default: the whole crop) of
    equal-size crops: channels computed on the whole crop (its margin gives the gradients
    their context), each cell summed by pooling. Equal to :func:`channel_features_at` of the
    box on the crops, for windows of scale ``q = w / W <= 1`` whose cells are whole pixels
    (``cell * q`` an integer): the training path.

    Args:
        crops: ``(N, 1 | 3, H0, W0)``, 0..255.
        bank, index: the features.
        region: the window inside every crop, ``w / h`` the window's aspect ratio.

    Returns:
        ``(N, K)`` float32.

    Raises:
        ShapeError: a region outside the crop, of another aspect ratio, of scale above 1 or
            with fractional cells.
    """
    x0 = _check_frames(crops)
    n, _, h0, w0 = x0.shape
    wh, ww = bank.window
    x, y, w, h = region if region is not None else (0, 0, w0, h0)
    q = w / ww
    p = bank.cell * q
    if (
        not (0 <= x and 0 <= y and x + w <= w0 and y + h <= h0)
        or abs(h - wh * q) > 1e-9
        or q > 1.0 + 1e-9
        or abs(p - round(p)) > 1e-9
        or round(p) < 1
    ):
        raise ShapeError(
            f"window {region} of {h0}x{w0} crops: needs the {wh}x{ww} window's aspect ratio, "
            f"a scale <= 1 and whole-pixel cells (cell {bank.cell} x scale {q:g})"
        )
    p = round(p)
    pts = bank.points(index, x0.device)
    k = sum(int(g[0].numel()) for g in pts.groups)
    ch = compute_channels(x0, bank.channels)[..., y : y + h, x : x + w]
    cells = F.avg_pool2d(ch, p).to(torch.float64) * float(p * p)  # (N, C, Hc, Wc) cell sums
    hc, wc = bank.grid
    lat = torch.zeros((n, ch.shape[1], hc + 1, wc + 1), dtype=torch.float64, device=x0.device)
    lat[:, :, 1:, 1:] = cells.cumsum(2).cumsum(3)
    norm = torch.full(
        (n,), 1.0 / (bank.cell * bank.cell * q * q), dtype=torch.float64, device=x0.device
    )
    logr = torch.full((n,), math.log(q), dtype=torch.float64, device=x0.device)
    out = _combine(lat.reshape(n, -1), pts, k, wc + 1, (hc + 1) * (wc + 1), norm, logr)
    return out.to(torch.float32)


class Lattice(NamedTuple):
    """One scan scale's cell lattice over whole frames (see :func:`scale_lattice`).

    ``values``: ``(B * Li * Lj * C,)`` float64 integral values at the lattice points, channels
    last: point ``(i, j)`` of frame ``b``, channel ``c`` at ``((b * Li + i) * Lj + j) * C + c``.
    ``shape``: ``(Li, Lj)``.
    ``origins``: ``(M, 2)`` int64 lattice rows / columns of the windows' top-left corners;
    ``boxes``: ``(M, 4)`` their windows in frame pixels (the same for every frame).
    ``norm``, ``logr``: the area normalisation ``1 / (cell^2 r^2)`` and ``log r``.
    """

    values: torch.Tensor
    shape: tuple[int, int]
    channels: int
    origins: torch.Tensor
    boxes: torch.Tensor
    norm: float
    logr: float


#: on the CPU, :func:`_sample_product` reads this many bytes of table rows at a time, so its
#: intermediates stay in the cache (and are not fresh pages of memory on every call): 2-7x
#: faster on large frames than whole-frame passes, with the same values
_SAMPLE_CHUNK_BYTES = 1 << 20


def _sample_product(tab: torch.Tensor, ys: torch.Tensor, xs: torch.Tensor) -> torch.Tensor:
    """Bilinear reads of channels-last ``tab (B, H1, W1, C)`` at every ``(ys[a], xs[b])``
    (table indices, clamped to the table): rows first, then columns ->
    ``(B, len(ys), len(xs), C)``.

    Frame by frame, on ``(H1, W * C)`` views of the table: rows are copied (the first pass)
    and C-value runs (the second), which is 1.2-2.5x faster than indexing the 4-d table. On
    the CPU both passes go a band of rows at a time (:data:`_SAMPLE_CHUNK_BYTES`) over the
    columns the reads need; the arithmetic is the same, so are the values. On a GPU one pass
    reads whole rows (no host synchronisation)."""
    b, h1, w1, c = tab.shape
    ys = ys.clamp(0, h1 - 1)
    xs = xs.clamp(0, w1 - 1)
    y0 = ys.floor().clamp(max=max(h1 - 2, 0)).long()
    x0 = xs.floor().clamp(max=max(w1 - 2, 0)).long()
    fy = (ys - y0).to(tab.dtype)[:, None]
    fx = (xs - x0).to(tab.dtype)[:, None]
    y1 = (y0 + 1).clamp(max=h1 - 1)
    x1 = (x0 + 1).clamp(max=w1 - 1)
    n_y, n_x = ys.numel(), xs.numel()
    out = torch.empty((b, n_y, n_x, c), dtype=tab.dtype, device=tab.device)
    if n_y == 0 or n_x == 0:
        return out
    lo, hi, band = 0, w1, n_y  # off the CPU: one pass, no host read of the columns
    if tab.device.type == "cpu":
        lo, hi = int(x0.min()), int(x1.max()) + 1  # the columns read
        band = max(1, _SAMPLE_CHUNK_BYTES // ((hi - lo) * c * tab.element_size()))
    w = hi - lo
    x0, x1 = x0 - lo, x1 - lo
    for i in range(b):
        t2 = tab[i, :, lo:hi].reshape(h1, w * c)
        for r0 in range(0, n_y, band):
            r1 = min(r0 + band, n_y)
            rows = torch.lerp(
                t2.index_select(0, y0[r0:r1]), t2.index_select(0, y1[r0:r1]), fy[r0:r1]
            )
            rows = rows.view(r1 - r0, w, c)
            torch.lerp(rows.index_select(1, x0), rows.index_select(1, x1), fx, out=out[i, r0:r1])
    return out


def scale_lattice(
    ints: ChannelIntegrals,
    bank: ChannelBank,
    scale: float,
    step: int | tuple[int, int] = 1,
    *,
    outside: tuple[int, int] = (0, 0),
    frame_pad: tuple[float, float] = (0.0, 0.0),
    keep_windows: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> Lattice | None:
    """The cell lattice of windows of ``scale`` (x the bank's window) over whole frames.

    Windows start at every ``step``-th lattice point (``step * cell * scale`` frame pixels
    apart; ``step = (rows, columns)`` for different vertical and horizontal steps) and lie
    inside the frame, or up to ``outside = (rows, columns)`` cells of this scale beyond each of
    its edges when the frames of ``ints`` were padded by ``frame_pad = (top and bottom, left
    and right)`` pixels (at least that much). Any feature of a window at lattice origin
    ``(i0, j0)`` reads the points ``(i0 + i, j0 + j)``; the values equal
    :func:`channel_features_at` of its box (in the frames of ``ints``).

    ``keep_windows(boxes (M, 4)) -> (M,) bool`` keeps only some of the windows (frame pixels, as
    the lattice's ``boxes``): the lattice then covers the rows and columns those windows read,
    and nothing else is sampled. A function whose attribute ``by_row`` is true says that its
    answer depends on a window's y and height only (a ground plane's sizes): it is asked about
    the first window of each lattice row, and the answer holds for the whole row.

    Returns:
        a :class:`Lattice` (boxes in the coordinates of the frame without its padding), or
        ``None`` when no window fits (or ``keep_windows`` keeps none).
    """
    wh, ww = bank.window
    fh, fw = ints.frame_size
    py, px = (float(v) for v in frame_pad)
    ky, kx = (int(v) for v in outside)
    if ky < 0 or kx < 0:
        raise ConfigError(f"outside must be >= 0 cells, got {outside!r}")
    fh, fw = fh - 2 * py, fw - 2 * px  # the frame proper
    lev = int(box_levels(torch.tensor(float(scale), dtype=torch.float64), ints.max_level()))
    f = float(1 << lev)
    r = float(scale) / f
    d = bank.cell * r  # lattice spacing in level pixels
    cs = bank.cell * float(scale)  # ... in frame pixels
    y_start, x_start = py - ky * cs, px - kx * cs  # first lattice point, padded-frame pixels
    if y_start < -1e-6 or x_start < -1e-6:
        raise ConfigError(
            f"frame_pad {frame_pad!r} px is less than {outside!r} cells at scale {scale:g}"
        )
    hc, wc = bank.grid
    li = math.floor((fh + 2 * ky * cs - wh * scale) / cs + 1e-9)
    lj = math.floor((fw + 2 * kx * cs - ww * scale) / cs + 1e-9)
    if li < 0 or lj < 0:
        return None
    st_i, st_j = (step, step) if isinstance(step, int) else (int(step[0]), int(step[1]))
    if st_i < 1 or st_j < 1:
        raise ConfigError(f"lattice steps must be >= 1, got {step!r}")
    n_i = li // st_i + 1
    n_j = lj // st_j + 1
    rows_i = (n_i - 1) * st_i + hc + 1
    cols_j = (n_j - 1) * st_j + wc + 1
    dev = ints.device
    oi = torch.arange(n_i, device=dev) * st_i
    oj = torch.arange(n_j, device=dev) * st_j
    gi, gj = torch.meshgrid(oi, oj, indexing="ij")
    origins = torch.stack((gi.reshape(-1), gj.reshape(-1)), 1)
    boxes = torch.stack(
        (
            origins[:, 1].to(torch.float64) * cs - kx * cs,
            origins[:, 0].to(torch.float64) * cs - ky * cs,
            torch.full((origins.shape[0],), ww * float(scale), dtype=torch.float64, device=dev),
            torch.full((origins.shape[0],), wh * float(scale), dtype=torch.float64, device=dev),
        ),
        1,
    )
    i0 = j0 = 0
    if keep_windows is not None:
        if getattr(keep_windows, "by_row", False):  # one window per row answers for the row
            row = keep_windows(boxes.view(n_i, n_j, 4)[:, 0]).to(dev)
            keep = row[:, None].expand(n_i, n_j).reshape(-1)
        else:
            keep = keep_windows(boxes).to(dev)
        if not bool(keep.any()):
            return None
        origins, boxes = origins[keep], boxes[keep]
        i0, j0 = int(origins[:, 0].min()), int(origins[:, 1].min())
        rows_i = int(origins[:, 0].max()) - i0 + hc + 1
        cols_j = int(origins[:, 1].max()) - j0 + wc + 1
        origins = origins - torch.tensor([i0, j0], device=dev)
    ys = (torch.arange(rows_i, dtype=torch.float64, device=dev) + i0) * d + y_start / f
    xs = (torch.arange(cols_j, dtype=torch.float64, device=dev) + j0) * d + x_start / f
    # the level's channels are computed here, after keep_windows: an octave none of whose
    # windows is kept (the ground plane's sizes) is never computed
    lat = _sample_product(ints.level(lev), ys, xs)  # (B, rows_i, cols_j, C)
    return Lattice(
        lat.reshape(-1),
        (rows_i, cols_j),
        int(lat.shape[-1]),
        origins,
        boxes,
        1.0 / (bank.cell * bank.cell * r * r),
        math.log(r),
    )


class ChannelFeatures(nn.Module):
    """Module wrapper of :func:`channel_features_at` on frames; stores the bank and index."""

    def __init__(self, bank: ChannelBank, index: torch.Tensor | None = None) -> None:
        super().__init__()
        self.bank = bank
        self.index = index

    def forward(self, frames: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
        """``frames (B, C, H, W)``, ``boxes (B, N, 4)`` -> ``(B, N, K)``."""
        return channel_features_at(self.bank.integrals(frames), boxes, self.bank, self.index)
