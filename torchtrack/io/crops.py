"""Crop datasets for training detectors: folders of labelled crops and random windows of images.

Documented conversions (the same for training and for calibration crops):

* **Channels.** Every image is decoded as 8-bit grayscale (``cv2.IMREAD_GRAYSCALE``: RGB and
  RGBA become BT.601 luma, 16-bit images are scaled to 8 bits), so crops with mixed channel
  counts load into one ``(N, 1, H, W)`` uint8 tensor; with ``colour=True`` as 8-bit RGB
  (``(N, 3, H, W)``; grayscale files get R = G = B), for detectors on colour channels.
* **Sizes.** With ``region = (x, y, w, h)`` and ``crop_size = (H0, W0)`` a crop is first resized
  to ``crop_size`` when it has another size, then the region is cut out (INRIA: 96x160 crops,
  the central 64x128 window). The result is resized to the ``window`` when it differs. Resizing
  uses area averaging (``cv2.INTER_AREA``), which matches what the integral-image features see
  in a box at that scale. The number of resized crops is reported in ``CropSet.resized``.
* **Bad files.** Files that are not images or cannot be decoded are skipped and listed with
  the reason in ``CropSet.skipped``; with ``strict=True`` they raise :class:`DataError` naming
  every such path. Hidden files and ``README*`` / ``*.txt`` / ``*.md`` notes are ignored.
"""

from __future__ import annotations

import fnmatch
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.errors import ConfigError, DataError

__all__ = [
    "IMAGE_SUFFIXES",
    "CropSet",
    "check_crop_folders",
    "crops_from_boxes",
    "list_image_files",
    "load_crops",
    "load_images",
    "mirror",
    "read_gray",
    "read_image",
    "sample_boxes",
    "sample_windows",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".pbm", ".bmp", ".tif", ".tiff", ".webp")
_NOTES = (".txt", ".md", ".csv", ".json", ".toml")


@dataclass
class CropSet:
    """Window-sized grayscale crops.

    Attributes:
        images: ``(N, 1, H, W)`` uint8.
        sources: one string per row: the file path, ``"<path>#flip"`` for a mirror image, or
            ``"<path>@x,y,w,h"`` for a window sampled from an image.
        skipped: ``(path, reason)`` for every file that could not be used.
        resized: how many crops had to be resized (see the module notes).
    """

    images: torch.Tensor
    sources: list[str]
    skipped: list[tuple[str, str]] = field(default_factory=list)
    resized: int = 0

    def __len__(self) -> int:
        return int(self.images.shape[0])

    def subset(self, keep: list[int] | torch.Tensor) -> CropSet:
        idx = torch.as_tensor(keep, dtype=torch.int64)
        return CropSet(
            self.images[idx], [self.sources[i] for i in idx.tolist()], self.skipped, self.resized
        )

    @staticmethod
    def concat(parts: list[CropSet]) -> CropSet:
        if not parts:
            raise DataError("no crop sets to concatenate")
        return CropSet(
            torch.cat([p.images for p in parts]),
            [s for p in parts for s in p.sources],
            [s for p in parts for s in p.skipped],
            sum(p.resized for p in parts),
        )


def _decode(path: str | os.PathLike, colour: bool = False) -> tuple[np.ndarray | None, str]:
    """``(image, "")`` or ``(None, why it cannot be used)``, through the one image decoder of
    :mod:`torchtrack.io.video` (the frame reader uses the same one): ``(H, W)`` uint8 luma, or
    with ``colour`` ``(H, W, 3)`` uint8 RGB (gray files replicated)."""
    from torchtrack.io.video import decode_image

    try:
        img = decode_image(path, cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    except DataError as exc:
        return None, str(exc)
    if colour:
        if img.ndim != 3 or img.shape[2] != 3:
            return None, f"image {path} did not decode to three colour channels"
        return np.ascontiguousarray(img[:, :, ::-1]), ""
    if img.ndim != 2:
        return None, f"image {path} did not decode to one gray channel"
    return img, ""


def read_gray(path: str | os.PathLike) -> np.ndarray | None:
    """Decode an image file as ``(H, W)`` uint8 luma; ``None`` when it is not a decodable image
    (missing, empty, truncated, corrupt)."""
    return _decode(path, False)[0]


def read_image(path: str | os.PathLike, colour: bool = False) -> np.ndarray | None:
    """Decode an image file as ``(H, W)`` uint8 luma, or with ``colour`` as ``(H, W, 3)`` uint8
    RGB (grayscale files replicated); ``None`` when it is not a decodable image."""
    return _decode(path, colour)[0]


def check_crop_folders(groups: dict[str, list], positives: str) -> None:
    """Refuse a crop folder named twice under one option (its crops would count twice) or under
    ``positives`` and another option (every crop of it both a positive and a negative: a fit
    that can only learn the positive rate). ``groups``: option name -> folders, in the order
    given; folders are compared by :func:`~torchtrack.io.atomic.path_key`.

    Raises:
        ConfigError: naming the option and the folder.
    """
    from torchtrack.io.atomic import path_key

    found: dict[str, str] = {}  # a folder -> the option that named it last
    for option, folders in groups.items():
        for x in folders:
            k = path_key(x)
            if found.get(k) == option:
                raise ConfigError(f"{option} names {x!r} twice: its crops would count twice")
            if option != positives and found.get(k) == positives:
                raise ConfigError(
                    f"{option} names {x!r}, a folder of {positives}: its crops would be both "
                    "positives and negatives"
                )
            found[k] = option


def list_image_files(folder: str | os.PathLike) -> tuple[list[Path], list[tuple[str, str]]]:
    """Candidate files of a crop folder (sorted, not recursive) and the files skipped by name.

    Raises:
        DataError: the folder does not exist.
    """
    from torchtrack.io.video import is_broken_link

    root = Path(folder)
    if not root.is_dir():
        raise DataError(f"crop folder {str(root)!r} does not exist or is not a folder")
    files, skipped = [], []
    for p in sorted(root.iterdir()):
        name = p.name
        # a broken symbolic link stays a candidate: reading it fails like any unreadable
        # crop (skipped and counted, or refused with strict), never dropped unseen
        if name.startswith(".") or not (p.is_file() or is_broken_link(p)):
            continue
        low = name.lower()
        if low.startswith("readme") or low.endswith(_NOTES):
            continue
        if not low.endswith(IMAGE_SUFFIXES):
            skipped.append((str(p), "not an image file (unknown extension)"))
            continue
        files.append(p)
    return files, skipped


def _to_window(
    img: np.ndarray,
    window: tuple[int, int],
    region: tuple[int, int, int, int] | None,
    crop_size: tuple[int, int] | None,
    keep_context: bool = False,
) -> tuple[np.ndarray, bool]:
    resized = False
    if region is not None:
        if crop_size is not None and img.shape[:2] != tuple(crop_size):
            img = cv2.resize(img, (crop_size[1], crop_size[0]), interpolation=cv2.INTER_AREA)
            resized = True
        if keep_context:
            return np.ascontiguousarray(img), resized
        x, y, w, h = region
        img = img[y : y + h, x : x + w]
    if img.shape[:2] != tuple(window):
        img = cv2.resize(img, (window[1], window[0]), interpolation=cv2.INTER_AREA)
        resized = True
    return np.ascontiguousarray(img), resized


def _check_geometry(window, region, crop_size) -> None:
    if len(window) != 2 or any(not isinstance(v, int) or v < 1 for v in window):
        raise ConfigError(f"window must be (H, W) positive integers, got {window!r}")
    if region is not None:
        if crop_size is None:
            raise ConfigError("region (x, y, w, h) needs crop_size (H, W), the size it refers to")
        if len(region) != 4:
            raise ConfigError(f"region must be (x, y, w, h), got {list(region)!r}")
        if len(crop_size) != 2:
            raise ConfigError(f"crop_size must be (H, W), got {list(crop_size)!r}")
        x, y, w, h = region
        if w < 1 or h < 1 or x < 0 or y < 0 or x + w > crop_size[1] or y + h > crop_size[0]:
            raise ConfigError(
                f"region {list(region)} (x, y, w, h) does not lie inside crop_size "
                f"{list(crop_size)} (H, W)"
            )


def load_crops(
    folder: str | os.PathLike,
    window: tuple[int, int],
    *,
    region: tuple[int, int, int, int] | None = None,
    crop_size: tuple[int, int] | None = None,
    exclude: set[str] | None = None,
    only: set[str] | None = None,
    pattern: str | None = None,
    strict: bool = False,
    progress: bool = False,
    colour: bool = False,
    keep_context: bool = False,
) -> CropSet:
    """Load a folder of crops as window-sized grayscale (or RGB) images.

    Args:
        folder: a folder of image files (not searched recursively).
        window: ``(H, W)`` of the detector window.
        region: ``(x, y, w, h)`` of the object inside each crop (in ``crop_size`` pixels).
        crop_size: ``(H0, W0)`` the region refers to; required with ``region``.
        exclude: file names (not paths) to leave out, e.g. a held-out test split.
        only: file names to keep (all others are left out).
        pattern: shell pattern the file names must match (e.g. ``"pos-*.pgm"``); files that
            do not match are left out silently.
        strict: raise instead of skipping unreadable or non-image files, and images under a
            quarter of the crop size in either side (skipped otherwise: resized more than 4x
            they would be a smear, not an example, e.g. a 1x1 PNG among the crops).
        progress: show a progress bar.
        colour: decode as RGB (``(N, 3, H, W)``).
        keep_context: with ``region``: keep the whole crop (resized to ``crop_size``), not
            only the region (the caller reads the window inside its context).

    Returns:
        a :class:`CropSet` in sorted file-name order.

    Raises:
        DataError: the folder is missing or has no usable image; with ``strict``, any bad file.
        ConfigError: inconsistent ``window`` / ``region`` / ``crop_size``.
    """
    _check_geometry(window, region, crop_size)
    files, skipped = list_image_files(folder)
    if pattern is not None:
        files = [p for p in files if fnmatch.fnmatch(p.name, pattern)]
        skipped = [s for s in skipped if fnmatch.fnmatch(Path(s[0]).name, pattern)]
    if exclude:
        files = [p for p in files if p.name not in exclude]
    if only is not None:
        files = [p for p in files if p.name in only]
    if progress:
        from tqdm import tqdm

        files_iter = tqdm(files, desc=f"reading {Path(folder).name}", unit="crop", leave=False)
    else:
        files_iter = files
    imgs, sources, resized = [], [], 0
    want = tuple(crop_size) if region is not None else tuple(window)  # the size crops become
    for p in files_iter:
        img, why = _decode(p, colour)
        if img is None:
            skipped.append((str(p), why))
            continue
        if img.shape[0] * 4 < want[0] or img.shape[1] * 4 < want[1]:
            # blown up more than 4x it would be a smear, not an example of the object
            skipped.append(
                (str(p), f"{img.shape[0]}x{img.shape[1]} px, under a quarter of the "
                         f"{want[0]}x{want[1]} crop it is resized to")
            )  # fmt: skip
            continue
        win, was_resized = _to_window(img, window, region, crop_size, keep_context)
        resized += was_resized
        imgs.append(win)
        sources.append(str(p))
    skipped.sort()
    if strict and skipped:
        lines = "\n  ".join(f"{path}: {why}" for path, why in skipped)
        raise DataError(
            f"{len(skipped)} unusable file(s) in {str(folder)!r} (strict mode):\n  {lines}"
        )
    if not imgs:
        # with the reason: the caller's warnings listing them come only after a load
        extra = (
            f" ({len(skipped)} unusable file(s), e.g. {skipped[0][0]}: {skipped[0][1]})"
            if skipped
            else ""
        )
        raise DataError(f"crop folder {str(folder)!r} has no usable image{extra}")
    stacked = torch.from_numpy(np.stack(imgs))
    images = stacked.permute(0, 3, 1, 2).contiguous() if colour else stacked[:, None]
    return CropSet(images, sources, skipped, resized)


def mirror(crops: CropSet) -> CropSet:
    """Append the left-right mirror image of every crop (sources get a ``#flip`` suffix)."""
    return CropSet(
        torch.cat((crops.images, crops.images.flip(-1))),
        crops.sources + [s + "#flip" for s in crops.sources],
        crops.skipped,
        crops.resized,
    )


def load_images(
    paths: list[str | os.PathLike], *, strict: bool = False, colour: bool = False
) -> tuple[list[np.ndarray], list[str], list[tuple[str, str]]]:
    """Read whole images (for negative windows) as grayscale ``(H, W)`` (or with ``colour``
    RGB ``(H, W, 3)``) uint8 arrays.

    Returns:
        ``(images, paths_used, skipped)``.

    Raises:
        DataError: no image could be read, or (``strict``) any could not.
    """
    imgs, used, skipped = [], [], []
    for p in paths:
        img, why = _decode(p, colour)
        if img is None:
            skipped.append((str(p), why))
            continue
        imgs.append(img)
        used.append(str(p))
    if strict and skipped:
        raise DataError("unusable image(s) (strict mode): " + ", ".join(s for s, _ in skipped))
    if not imgs:
        raise DataError(f"none of the {len(paths)} negative image(s) could be read")
    return imgs, used, skipped


def crops_from_boxes(
    img: np.ndarray, boxes: np.ndarray | torch.Tensor, window: tuple[int, int]
) -> np.ndarray:
    """Cut ``boxes (N, 4)`` (x, y, w, h, rounded to whole pixels, inside the image) out of a
    grayscale ``img (H, W)`` and resize each to ``window`` -> ``(N, H_win, W_win)`` uint8."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    out = np.empty((b.shape[0], window[0], window[1]), dtype=np.uint8)
    ih, iw = img.shape
    for i, (x, y, w, h) in enumerate(b):
        x0 = int(np.clip(round(x), 0, iw - 1))
        y0 = int(np.clip(round(y), 0, ih - 1))
        x1 = int(np.clip(round(x + w), x0 + 1, iw))
        y1 = int(np.clip(round(y + h), y0 + 1, ih))
        out[i] = cv2.resize(img[y0:y1, x0:x1], (window[1], window[0]), interpolation=cv2.INTER_AREA)
    return out


def sample_boxes(
    sizes: list[tuple[int, int]],
    window: tuple[int, int],
    n: int,
    *,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    generator: torch.Generator | None = None,
) -> list[tuple[int, int, int, int, int]]:
    """``n`` random windows ``(image, x, y, w, h)`` (whole pixels) of the window's aspect ratio
    in images of ``sizes`` ``(H_i, W_i)``.

    The image is drawn uniformly among those at least ``min_scale`` times the window, the scale
    log-uniformly in ``[min_scale, max_scale]`` (capped by what fits the image), the position
    uniformly.

    Raises:
        ConfigError: ``n < 0`` or a bad ``min_scale``.
        DataError: no image is large enough.
    """
    if n < 0:
        raise ConfigError(f"number of windows must be >= 0, got {n}")
    if not (min_scale > 0 and math.isfinite(min_scale)):
        raise ConfigError(f"min_scale must be a positive number, got {min_scale!r}")
    hw, ww = window
    fits = [i for i, (h, w) in enumerate(sizes) if h >= hw * min_scale and w >= ww * min_scale]
    if not fits:
        raise DataError(
            f"no negative image is at least {min_scale:g} x the {hw}x{ww} (HxW) window; "
            "use smaller windows or larger images"
        )
    u = torch.rand((n, 4), generator=generator, dtype=torch.float64)
    pick = torch.randint(len(fits), (n,), generator=generator)
    out = []
    for j in range(n):
        i = fits[int(pick[j])]
        ih, iw = sizes[i]
        top = min(ih / hw, iw / ww)
        hi = top if max_scale is None else min(top, max_scale)
        lo = min(min_scale, hi)
        s = math.exp(math.log(lo) + float(u[j, 0]) * (math.log(hi) - math.log(lo)))
        w = max(1, min(iw, round(ww * s)))
        h = max(1, min(ih, round(hw * s)))
        x = int(float(u[j, 1]) * (iw - w + 1))
        y = int(float(u[j, 2]) * (ih - h + 1))
        out.append((i, x, y, w, h))
    return out


def sample_windows(
    images: list[np.ndarray],
    sources: list[str],
    window: tuple[int, int],
    n: int,
    *,
    min_scale: float = 1.0,
    max_scale: float | None = None,
    generator: torch.Generator | None = None,
) -> CropSet:
    """``n`` random windows (:func:`sample_boxes`) cut out of grayscale images and resized to
    the window (negatives).

    Args:
        images: grayscale ``(H_i, W_i)`` uint8 arrays.
        sources: one name per image (recorded in ``CropSet.sources`` with the box).
        window: ``(H, W)``.
        n: number of windows.
        min_scale, max_scale: window scale range relative to ``window``.
        generator: torch random generator (reproducible sampling).

    Raises:
        DataError: no image is large enough.
    """
    boxes = sample_boxes(
        [im.shape[:2] for im in images],
        window,
        n,
        min_scale=min_scale,
        max_scale=max_scale,
        generator=generator,
    )
    hw, ww = window
    out = np.empty((n, hw, ww), dtype=np.uint8)
    srcs = []
    for j, (i, x, y, w, h) in enumerate(boxes):
        out[j] = crops_from_boxes(images[i], np.array([[x, y, w, h]]), window)[0]
        srcs.append(f"{sources[i]}@{x},{y},{w},{h}")
    return CropSet(torch.from_numpy(out)[:, None], srcs)
