"""Per-pixel colour and local-ternary-pattern features (Jin et al. sec. 2).

Every pixel of a region gets

* four colour features: R, G, B and the luma Y (ITU-R BT.601, as ``rgb_to_gray``);
* eighteen texture codes: the upper and lower LTP_8,1 patterns (eq. 2-3) of the nine channel
  pairs RR, GG, BB, RG, RB, GR, GB, BR, BG, where the centre pixel comes from the first channel
  and the eight neighbours from the second (Jin et al.: "the central pixel is taken from the red
  channel and the other eight neighbor pixels are taken from the green channel").

Upper pattern bit u is ``g_u - g_c >= t``, lower pattern bit u is ``g_u - g_c <= -t`` (eq. 3),
both coded as ``sum_u 2^u bit_u`` in 0..255. Neighbour u sits at angle ``2 pi u / 8``
counter-clockwise from "right" (u = 0: right, 2: up, 4: left, 6: down), the ordering of
scikit-image's ``local_binary_pattern``. The default 3x3 square mask takes the diagonal
neighbours at the corner pixels (Jin's Fig. 2-3, Tan & Triggs); ``circular=True`` samples them
on the unit circle with bilinear interpolation exactly as scikit-image does, so that the upper
pattern with ``t = 0`` equals ``local_binary_pattern(img, 8, 1)`` bit for bit.

Single-channel input (documented fallback): the colour group is Y alone and the texture group
is the Y-Y pattern pair.

Pixels on the image border see replicated neighbours (compute on a crop with a one-pixel margin
to avoid that, as :func:`region_features` does).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from torchtrack.errors import ConfigError, DataError, ShapeError, is_integer, is_number
from torchtrack.features.integral import check_pixel_values, rgb_to_gray

__all__ = [
    "CHANNEL_PAIRS",
    "COLOUR_NAMES",
    "RIU2_TABLE",
    "TEXTURE_NAMES",
    "PixelFeatures",
    "colour_features",
    "ltp_codes",
    "pixel_features",
    "quantize_colour",
    "region_features",
    "texture_blocks",
]

#: (centre channel, neighbour channel) index pairs into R, G, B (Jin et al. sec. 2).
CHANNEL_PAIRS: tuple[tuple[int, int], ...] = (
    (0, 0),
    (1, 1),
    (2, 2),
    (0, 1),
    (0, 2),
    (1, 0),
    (1, 2),
    (2, 0),
    (2, 1),
)
_CH = "RGB"
COLOUR_NAMES: tuple[str, ...] = ("R", "G", "B", "Y")
#: Names of the 18 texture codes: ``RG+`` is the upper, ``RG-`` the lower pattern of pair RG.
TEXTURE_NAMES: tuple[str, ...] = tuple(
    f"{_CH[a]}{_CH[b]}{s}" for a, b in CHANNEL_PAIRS for s in ("+", "-")
)

# (dy, dx) of neighbour u at angle 2 pi u / 8 (rows grow downwards, so "up" is dy = -1).
_OFFSETS: tuple[tuple[int, int], ...] = (
    (0, 1),
    (-1, 1),
    (-1, 0),
    (-1, -1),
    (0, -1),
    (1, -1),
    (1, 0),
    (1, 1),
)


def _check(images: torch.Tensor) -> None:
    if not isinstance(images, torch.Tensor) or images.ndim != 4:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ShapeError(f"images must be (B, C, H, W), got {shape}")
    if images.shape[1] not in (1, 3):
        raise ShapeError(f"images must have 1 (gray) or 3 (RGB) channels, got C={images.shape[1]}")
    if images.dtype == torch.bool or images.is_complex():
        raise ShapeError(f"images must be integer or floating, got {images.dtype}")
    # NaN pixels gave NaN colour features (texture codes of 0), 16-bit levels were read on the
    # 8-bit scale; uint8 images need no pass over the pixels
    check_pixel_values(images, "images")


def _check_threshold(threshold) -> None:
    # True was a threshold of 1, '5' a TypeError; NaN and negatives were refused already
    if not is_number(threshold) or not 0 <= threshold < math.inf:
        raise ConfigError(f"LTP threshold must be >= 0 (a finite number), got {threshold!r}")


def _check_bins(bins) -> None:
    # int() read 2.5 as 2 bins and True as 1
    if not is_integer(bins) or not 1 <= bins <= 256:
        raise ConfigError(f"colour bins must be in 1..256 (an integer), got {bins!r}")


def _shift(p: torch.Tensor, dy: int, dx: int, h: int, w: int) -> torch.Tensor:
    return p[..., 1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]


def _neighbour(p: torch.Tensor, u: int, circular: bool, h: int, w: int) -> torch.Tensor:
    """Neighbour u of every pixel of the replicate-padded ``p (B, K, h + 2, w + 2)``."""
    if not circular or u % 2 == 0:
        return _shift(p, *_OFFSETS[u], h, w)
    # scikit-image (_texture.pyx + interpolation.pxd): coordinates rounded to 5 decimals,
    # top = (1-dc) I[minr, minc] + dc I[minr, maxc], bottom likewise on maxr, out =
    # (1-dr) top + dr bottom, with minr = floor(r) etc. Same operation order, float64.
    a = 2 * math.pi * u / 8
    r, c = round(-math.sin(a), 5), round(math.cos(a), 5)
    minr, maxr, minc, maxc = math.floor(r), math.ceil(r), math.floor(c), math.ceil(c)
    dr, dc = r - minr, c - minc
    top = (1 - dc) * _shift(p, minr, minc, h, w) + dc * _shift(p, minr, maxc, h, w)
    bottom = (1 - dc) * _shift(p, maxr, minc, h, w) + dc * _shift(p, maxr, maxc, h, w)
    return (1 - dr) * top + dr * bottom


def ltp_codes(
    centre: torch.Tensor,
    neighbour: torch.Tensor,
    threshold: float = 5.0,
    *,
    circular: bool = False,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Upper and lower LTP_8,1 codes (Jin et al. eq. 2-3) of centre/neighbour channel pairs.

    Args:
        centre: ``(B, K, H, W)`` channel giving the centre pixel ``g_c`` of each pair.
        neighbour: ``(B, K, H, W)`` channel giving the eight neighbours ``g_u``.
        threshold: t of eq. (3), in the images' intensity units (>= 0).
        circular: bilinear circle sampling of the diagonals (scikit-image's LBP) instead of the
            3x3 square mask.

    Returns:
        ``(upper, lower)``, each ``(B, K, H, W)`` int64 in 0..255.

    Raises:
        ShapeError: the shapes differ or are not 4-D. ConfigError: negative threshold.
    """
    if centre.ndim != 4 or centre.shape != neighbour.shape:
        raise ShapeError(
            f"centre and neighbour must be equal (B, K, H, W) tensors, got "
            f"{tuple(centre.shape)} and {tuple(neighbour.shape)}"
        )
    _check_threshold(threshold)
    if not circular and not centre.is_floating_point() and not neighbour.is_floating_point():
        upper, lower = _ltp_integer(centre, neighbour, threshold)
        return upper.long(), lower.long()
    # float32 is exact for differences of 8-bit values; circular sampling needs float64 to
    # reproduce scikit-image's interpolation bit for bit.
    dt = torch.float64 if circular or centre.dtype == torch.float64 else torch.float32
    gc = centre.to(dt)
    h, w = gc.shape[-2:]
    p = F.pad(neighbour.to(dt), (1, 1, 1, 1), mode="replicate")
    upper = torch.zeros(gc.shape, dtype=torch.int32, device=gc.device)
    lower = torch.zeros_like(upper)
    for u in range(8):  # the eight mask positions, each over the whole region at once
        d = _neighbour(p, u, circular, h, w) - gc
        upper |= (d >= threshold).to(torch.int32) << u
        lower |= (d <= -threshold).to(torch.int32) << u
    upper, lower = upper.long(), lower.long()
    return upper, lower


def _replicate_pad1(x: torch.Tensor) -> torch.Tensor:
    """One-pixel replicate padding of the last two axes, for any dtype."""
    x = torch.cat([x[..., :1, :], x, x[..., -1:, :]], -2)
    return torch.cat([x[..., :1], x, x[..., -1:]], -1)


def _ltp_integer(
    centre: torch.Tensor, neighbour: torch.Tensor, threshold: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Square-mask LTP of integer images as uint8 codes (the fast path of :func:`ltp_codes`).

    For integer differences d and a real t >= 0, ``d >= t`` is ``g_u >= g_c + ceil(t)`` and
    ``d <= -t`` is ``g_u <= g_c - ceil(t)``: the centre is offset once, the eight neighbours
    are compared to it (int16 for uint8 images, int64 otherwise) and the bits are added into
    uint8 codes.
    """
    small = centre.dtype == torch.uint8 and neighbour.dtype == torch.uint8
    wide = torch.int16 if small else torch.int64
    # 256 already clears every bit of 8-bit images; the cap keeps int16 from overflowing.
    t = min(math.ceil(threshold), 256) if small else math.ceil(threshold)
    gc = centre.to(wide)
    hi, lo = gc + t, gc - t
    h, w = gc.shape[-2:]
    p = _replicate_pad1(neighbour.to(wide))
    upper = torch.zeros(gc.shape, dtype=torch.uint8, device=gc.device)
    lower = torch.zeros_like(upper)
    for u in range(8):
        g = _shift(p, *_OFFSETS[u], h, w)
        upper.add_(torch.ge(g, hi).view(torch.uint8), alpha=1 << u)
        lower.add_(torch.le(g, lo).view(torch.uint8), alpha=1 << u)
    return upper, lower


def colour_features(images: torch.Tensor) -> torch.Tensor:
    """``(B, 3, H, W)`` -> ``(B, 4, H, W)`` float32 R, G, B, Y; ``(B, 1, H, W)`` -> Y alone."""
    _check(images)
    x = images.to(torch.float32)
    if x.shape[1] == 1:
        return x
    return torch.cat([x, rgb_to_gray(x)], 1)


def _pair_channels(x: torch.Tensor, dim: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Centre and neighbour channels of the :data:`CHANNEL_PAIRS` along ``dim`` (a single
    channel pairs with itself)."""
    if x.shape[dim] == 1:
        return x, x
    ci = torch.tensor([a for a, _ in CHANNEL_PAIRS], device=x.device)
    ni = torch.tensor([b for _, b in CHANNEL_PAIRS], device=x.device)
    return x.index_select(dim, ci), x.index_select(dim, ni)


def pixel_features(
    images: torch.Tensor, threshold: float = 5.0, *, circular: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Colour features and texture codes of every pixel (Jin et al. sec. 2).

    Args:
        images: ``(B, 3, H, W)`` RGB or ``(B, 1, H, W)`` gray, 0..255 (uint8 or float).
        threshold: LTP threshold t (eq. 3); 5 grey levels, Tan & Triggs' value for 8-bit images.
        circular: see :func:`ltp_codes`.

    Returns:
        ``colour (B, 4, H, W)`` float32 (R, G, B, Y; gray input: ``(B, 1, H, W)`` Y) and
        ``texture (B, 18, H, W)`` int64 codes in 0..255, ordered as :data:`TEXTURE_NAMES`
        (gray input: ``(B, 2, H, W)``, the Y-Y upper and lower patterns).

    Raises:
        ShapeError: not ``(B, C, H, W)`` with C in {1, 3}.
        DataError: pixel values not finite or outside [0, 255].
        ConfigError: ``threshold`` not a finite number >= 0.
    """
    _check(images)
    colour = colour_features(images)
    c, n = _pair_channels(images, 1)
    up, lo = ltp_codes(c, n, threshold, circular=circular)
    texture = torch.stack([up, lo], 2).flatten(1, 2)  # pair-major: RR+, RR-, GG+, ...
    return colour, texture


def _riu2_table() -> torch.Tensor:
    t = torch.empty(256, dtype=torch.long)
    for code in range(256):
        bits = [(code >> u) & 1 for u in range(8)]
        transitions = sum(bits[u] != bits[(u + 1) % 8] for u in range(8))
        t[code] = sum(bits) if transitions <= 2 else 9
    return t


#: Rotation-invariant uniform coding (Ojala et al. 2002, "riu2"): a pattern with at most two
#: 0/1 transitions around the circle maps to its number of set bits (0..8), any other to 9.
RIU2_TABLE: torch.Tensor = _riu2_table()


def texture_blocks(codes: torch.Tensor, blocks: str = "riu2") -> torch.Tensor:
    """Partition the 256 pattern codes into the value blocks of the weak classifiers:
    ``"full"`` keeps the 256 codes, ``"riu2"`` maps them to 10 rotation-invariant uniform
    classes (denser statistics from a few thousand pixels per frame)."""
    if blocks not in ("full", "riu2"):
        raise ConfigError(f"unknown texture blocks {blocks!r}; valid: full, riu2")
    if (
        not isinstance(codes, torch.Tensor)
        or codes.is_floating_point()
        or codes.is_complex()
        or codes.dtype == torch.bool
    ):
        got = codes.dtype if isinstance(codes, torch.Tensor) else type(codes).__name__
        raise ShapeError(f"texture_blocks: codes must be an integer tensor, got {got}")
    if codes.numel() and codes.dtype != torch.uint8:  # indices past 255: IndexError
        lo, hi = (int(v) for v in torch.aminmax(codes.long()))
        if lo < 0 or hi > 255:
            raise ShapeError(f"texture_blocks: codes must be in 0..255, got {lo}..{hi}")
    if blocks == "full":
        return codes
    return RIU2_TABLE.to(codes.device)[codes.long()]


def quantize_colour(colour: torch.Tensor, bins: int = 32) -> torch.Tensor:
    """Colour values in 0..255 -> int64 bin codes in ``0..bins-1`` (equal-width bins)."""
    _check_bins(bins)
    if not isinstance(colour, torch.Tensor) or colour.dtype == torch.bool or colour.is_complex():
        got = colour.dtype if isinstance(colour, torch.Tensor) else type(colour).__name__
        raise ShapeError(f"colour must be a tensor of real numbers, got {got}")
    if colour.is_floating_point() and bool(torch.isnan(colour).any()):  # NaN was bin 0
        raise DataError("quantize_colour: colour holds NaN values")
    return (colour.clamp(0, 255) * (bins / 256.0)).long().clamp_(0, bins - 1)


def region_features(
    frame: torch.Tensor,
    region: tuple[int, int, int, int],
    threshold: float = 5.0,
    colour_bins: int = 32,
    blocks: str = "full",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Quantised colour codes and texture codes of one frame region, as classifier inputs.

    The region is cut with a one-pixel margin where the frame has one, so its border pixels see
    their true neighbours. Codes come out pixel-major and as uint8 (every code is below 256), the
    layout the classifiers gather from; integer frames take the integer LTP path (no float
    conversion of the nine channel pairs).

    Args:
        frame: ``(C, H, W)`` uint8, C in {1, 3}.
        region: ``(x0, y0, x1, y1)`` integer pixel bounds inside the frame, x1 > x0, y1 > y0.
        threshold: LTP threshold. colour_bins: colour quantisation.
        blocks: texture code blocks (:func:`texture_blocks`).

    Returns:
        ``colour_codes (h*w, Fc)`` and ``texture_codes (h*w, Ft)`` uint8, pixels in row-major
        order of the region (Fc = 4, Ft = 18 for RGB; 1 and 2 for gray).

    Raises:
        ShapeError: bad frame. DataError: pixel values not finite or outside [0, 255].
        ConfigError: empty region or one outside the frame, bounds that are not integers, bad
        ``threshold``, ``colour_bins`` or ``blocks``.
    """
    if not isinstance(frame, torch.Tensor) or frame.ndim != 3:
        raise ShapeError("frame must be a (C, H, W) tensor")
    _check(frame.unsqueeze(0))
    _check_bins(colour_bins)
    if blocks not in ("full", "riu2"):
        raise ConfigError(f"unknown texture blocks {blocks!r}; valid: full, riu2")
    _check_threshold(threshold)
    _, hh, ww = frame.shape
    try:  # NaN was int()'s ValueError, True a bound of 1, 5.7 cut to 5
        bounds = [float(v) for v in region]
        whole = len(bounds) == 4 and all(math.isfinite(v) and v == int(v) for v in bounds)
    except (TypeError, ValueError, RuntimeError):
        whole = False
    if not whole or any(isinstance(v, bool) for v in region):
        raise ConfigError(f"region must be 4 integer pixel bounds (x0, y0, x1, y1), got {region!r}")
    x0, y0, x1, y1 = (int(v) for v in bounds)
    if not (0 <= x0 < x1 <= ww and 0 <= y0 < y1 <= hh):
        raise ConfigError(f"region {region} is empty or outside the {ww}x{hh} frame")
    mx0, my0 = max(x0 - 1, 0), max(y0 - 1, 0)
    mx1, my1 = min(x1 + 1, ww), min(y1 + 1, hh)
    crop = frame[:, my0:my1, mx0:mx1]
    sy, sx = y0 - my0, x0 - mx0
    h, w = y1 - y0, x1 - x0
    c, n = _pair_channels(crop, 0)
    if crop.is_floating_point():
        up, lo = ltp_codes(c[None], n[None], threshold)
        up, lo = up[0].to(torch.uint8), lo[0].to(torch.uint8)
    else:
        up, lo = _ltp_integer(c[None], n[None], threshold)
        up, lo = up[0], lo[0]
    tex = torch.stack([up, lo], 3)[:, sy : sy + h, sx : sx + w]  # (K, h, w, 2)
    tc = tex.permute(1, 2, 0, 3).reshape(h * w, -1)  # pair-major: RR+, RR-, GG+, ...
    if blocks == "riu2":
        tc = RIU2_TABLE.to(device=tc.device, dtype=torch.uint8)[tc.long()]
    colour = colour_features(crop[None, :, sy : sy + h, sx : sx + w])[0]  # (Fc, h, w)
    cc = (colour.clamp(0, 255) * (colour_bins / 256.0)).to(torch.uint8)
    cc = cc.clamp_(max=colour_bins - 1).permute(1, 2, 0).reshape(h * w, -1)
    return cc, tc


class PixelFeatures(nn.Module):
    """Module wrapper of :func:`pixel_features`; stores the arguments only."""

    def __init__(self, threshold: float = 5.0, circular: bool = False) -> None:
        super().__init__()
        self.threshold = threshold
        self.circular = circular

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(B, C, H, W)`` -> ``(colour (B, 4, H, W), texture (B, 18, H, W))``."""
        return pixel_features(images, self.threshold, circular=self.circular)
