"""Training a detector on integral channel features with boosted trees, rounds of hard-negative
mining and a soft cascade (Dollár et al.'s ICF / ACF recipe), calibrated like Chateau et al.'s.

Every sample is a *window in an image*, read by the same code that scores boxes and scans
frames (:func:`~torchtrack.features.channels.channel_features_at`), so training sees exactly
what detection sees:

* positives: each positive crop in colour *with its context* (INRIA: the whole 96x160 crop
  around the 64x128 window, so that the window's gradients see the margin), its mirror image,
  and copies downscaled by ``data.positive_scales`` (small objects at their own resolution);
* negatives: negative crops (the whole crop is the window), random windows of the negative
  images (scales ``data.negative_min_scale`` to what fits, read at the image's resolution: no
  crop is resized), and the windows mined in every round.

Steps of :func:`train_channel_detector`:

1. Load; hold out ``learn.calibration_fraction`` (paper: 30%) of the source groups of each
   class for calibration (a crop, its mirror and its downscaled copies stay together; the
   negative images of the held-out side are never mined).
2. Compute every feature of the candidate pool (:func:`~torchtrack.features.channels.channel_bank`)
   on every training window and code it once into 256 quantile bins.
3. Rounds ``r = 0 .. R`` (``R = mining.rounds``): boost ``max(32, n_trees / 4^(R - r))`` trees
   (Dollár's schedule 32, 128, 512, 2048 for ``R = 3``); after each round but the last, scan
   the training negative images with the constant soft cascade ``mining.margin`` and add the
   windows that score at least ``mining.margin`` (see :class:`~torchtrack.detect.config.MiningConfig`).
4. Calibrate (Platt or isotonic) on the held-out windows; set the soft cascade from the
   held-out positives (``learn.cascade``: by default one constant threshold that keeps all but
   ``learn.cascade_miss`` of the positives the calibration finds, see
   :func:`held_out_cascade_threshold`); keep only the features the trees use.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import torch
from torch.nn import functional as F

from torchtrack.detect.config import TrainConfig, excluded_names
from torchtrack.detect.detector import Detector
from torchtrack.detect.evaluate import detection_rate_at_fpr, roc_auc
from torchtrack.detect.training import _image_paths
from torchtrack.errors import ConfigError, DataError, TrainingWarning
from torchtrack.features.channels import ChannelBank, channel_bank, window_features
from torchtrack.io.crops import CropSet, load_crops, load_images, sample_boxes

__all__ = [
    "WindowSet",
    "channel_window_features",
    "fit_box_regression",
    "mine_windows",
    "train_channel_detector",
]


@dataclass
class WindowSet:
    """Windows in images: ``boxes (n, 4)`` x, y, w, h in ``images[image[k]]``."""

    images: list[torch.Tensor]  # (C, H, W) uint8
    image: torch.Tensor  # (n,) int64
    boxes: torch.Tensor  # (n, 4) float64
    sources: list[str]

    def __len__(self) -> int:
        return int(self.image.numel())

    def subset(self, keep: torch.Tensor) -> WindowSet:
        idx = torch.as_tensor(keep, dtype=torch.int64)
        return WindowSet(
            self.images, self.image[idx], self.boxes[idx], [self.sources[i] for i in idx.tolist()]
        )


@dataclass
class _Crops:
    """Equal-size crops with one window each (positives or negative crops)."""

    images: torch.Tensor  # (N, C, H0, W0) uint8
    region: tuple[int, int, int, int]
    sources: list[str]

    def __len__(self) -> int:
        return int(self.images.shape[0])


def _crop_features(crops: _Crops, bank: ChannelBank, index=None, chunk: int = 256) -> torch.Tensor:
    parts = [
        window_features(crops.images[i : i + chunk], bank, crops.region, index)
        for i in range(0, len(crops), chunk)
    ]
    return torch.cat(parts) if parts else torch.zeros((0, len(bank)))


def channel_window_features(
    windows: WindowSet, bank: ChannelBank, index: torch.Tensor | None = None
) -> torch.Tensor:
    """Features ``(n, K)`` float32 of windows in images, image by image (one set of channel
    integral images per image)."""
    k = len(bank) if index is None else int(torch.as_tensor(index).numel())
    out = torch.empty((len(windows), k), dtype=torch.float32)
    for i in torch.unique(windows.image).tolist():
        rows = torch.nonzero(windows.image == i).flatten()
        img = windows.images[i][None]
        ints = bank.integrals(img)
        for r0 in range(0, rows.numel(), 1024):
            r = rows[r0 : r0 + 1024]
            out[r] = bank.features_at(ints, windows.boxes[r][None], index, check=False)[0]
    return out


def _scaled_images(
    images: torch.Tensor,
    region: tuple[int, int, int, int],
    q: float,
    setting: str = "data.positive_scales",
) -> tuple[torch.Tensor, tuple[int, int, int, int]]:
    """Crops ``(N, C, H, W)`` uint8 downscaled by ``q`` (area averaging) and their region;
    ``setting`` names where ``q`` came from in the error."""
    if q == 1.0:
        return images, region
    reg = [v * q for v in region]
    if any(abs(v - round(v)) > 1e-9 for v in reg):
        raise ConfigError(f"{setting}: {q} x the window region {list(region)} is not whole pixels")
    h0, w0 = images.shape[-2:]
    size = (round(h0 * q), round(w0 * q))
    imgs = F.interpolate(images.float(), size=size, mode="area").round().to(torch.uint8)
    return imgs, tuple(round(v) for v in reg)


def _scaled(crops: _Crops, q: float) -> _Crops:
    """The crops downscaled by ``q`` (area averaging) with their region."""
    if q == 1.0:
        return crops
    imgs, reg = _scaled_images(crops.images, crops.region, q)
    return _Crops(imgs, reg, [f"{s}#s{q:g}" for s in crops.sources])


def _mirrored(crops: _Crops) -> _Crops:
    x, y, w, h = crops.region
    w0 = crops.images.shape[-1]
    return _Crops(
        crops.images.flip(-1), (w0 - x - w, y, w, h), [s + "#flip" for s in crops.sources]
    )


def _concat(parts: list[_Crops]) -> _Crops:
    return _Crops(
        torch.cat([p.images for p in parts]), parts[0].region, [s for p in parts for s in p.sources]
    )


def _gray(images: torch.Tensor) -> torch.Tensor:
    """``(N, 3, H, W)`` uint8 RGB -> the same with R = G = B = the BT.601 luma (rounded)."""
    from torchtrack.features.integral import rgb_to_gray

    g = rgb_to_gray(images.float()).round().clamp(0, 255).to(torch.uint8)
    return g.expand(-1, 3, -1, -1).contiguous()


def _blurred(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """``(N, C, H, W)`` uint8 blurred by a Gaussian of sd ``sigma`` pixels (kornia, reflected
    borders), rounded back to uint8."""
    import kornia

    k = 2 * max(1, math.ceil(3.0 * sigma)) + 1
    out = torch.empty_like(images)
    for i in range(0, images.shape[0], 256):  # bounded float copies
        x = images[i : i + 256].float()
        y = kornia.filters.gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="reflect")
        out[i : i + 256] = y.round().clamp(0, 255).to(torch.uint8)
    return out


def _blur_pick(n: int, share: float, seed: int) -> list[int]:
    """Which of ``n`` items get a blurred copy: ``round(share * n)`` of them, a seeded pick in
    their order."""
    if share >= 1.0:
        return list(range(n))
    g = torch.Generator().manual_seed(seed)
    return sorted(torch.randperm(n, generator=g)[: round(share * n)].tolist())


def _folder_pattern(entry: str) -> tuple[str, str | None]:
    p = Path(entry)
    if any(c in p.name for c in "*?["):
        return str(p.parent), p.name
    return entry, None


@dataclass
class ChannelData:
    """Everything a channel training run reads (see the module notes)."""

    positives: list[_Crops]  # one per positive scale, mirrors included
    negative_crops: _Crops | None
    images: list[torch.Tensor]
    image_sources: list[str]
    skipped: list[tuple[str, str]]


def _positive_crops(
    cfg: TrainConfig, exclude: set[str], colour: bool, progress: bool
) -> tuple[CropSet, _Crops]:
    """The positive crops of ``cfg`` with their context, and as :class:`_Crops` with the
    window's region inside them."""
    d = cfg.data
    window = (int(cfg.window[0]), int(cfg.window[1]))
    region = tuple(d.region) if d.region is not None else None
    crop_size = tuple(d.crop_size) if d.crop_size is not None else None
    sets = [
        load_crops(
            folder,
            window,
            region=region,
            crop_size=crop_size,
            exclude=exclude,
            pattern=pat,
            strict=d.strict,
            progress=progress,
            colour=colour,
            keep_context=True,
        )
        for folder, pat in map(_folder_pattern, d.positives)
    ]
    pos = CropSet.concat(sets)
    box = region if region is not None else (0, 0, window[1], window[0])
    return pos, _Crops(pos.images, tuple(int(v) for v in box), pos.sources)


def load_channel_data(cfg: TrainConfig, *, progress: bool = False) -> ChannelData:
    """Read the positive crops (with context), negative crops and negative images of ``cfg``.

    Raises:
        DataError: a missing or empty folder, no usable negative image; with ``data.strict``,
            any unusable file.
    """
    d = cfg.data
    window = (int(cfg.window[0]), int(cfg.window[1]))
    colour = cfg.features.channel_set().colour
    exclude = excluded_names(d)
    pos, base = _positive_crops(cfg, exclude, colour, progress)
    skipped = list(pos.skipped)
    if d.positive_jitter > 0:  # a copy of every crop shifted by up to positive_jitter pixels
        g = torch.Generator().manual_seed(int(cfg.seed) + 7)
        j = int(d.positive_jitter)
        shifts = torch.randint(-j, j + 1, (len(base), 2), generator=g).tolist()
        moved = torch.stack(
            [
                torch.roll(im, (dy, dx), (-2, -1))
                for im, (dy, dx) in zip(base.images, shifts, strict=True)
            ]
        )
        base = _concat([base, _Crops(moved, base.region, [s + "#jitter" for s in base.sources])])
    if d.gray_copies and colour:
        base = _concat(
            [base, _Crops(_gray(base.images), base.region, [s + "#gray" for s in base.sources])]
        )
    if d.blur_copies > 0:  # blurred copies: a model that holds on soft or upscaled video
        pick = _blur_pick(len(base), float(d.blur_share), int(cfg.seed) + 11)
        blurred = _blurred(base.images[pick], float(d.blur_copies))
        base = _concat(
            [base, _Crops(blurred, base.region, [base.sources[i] + "#blur" for i in pick])]
        )
    if d.mirror_positives:
        base = _concat([base, _mirrored(base)])
    positives = [_scaled(base, float(q)) for q in d.positive_scales]
    neg_crops = None
    if d.negatives:
        negs = [
            load_crops(folder, window, exclude=exclude, pattern=pat, strict=d.strict, colour=colour)
            for folder, pat in map(_folder_pattern, d.negatives)
        ]
        skipped += [s for n in negs for s in n.skipped]
        nc = CropSet.concat(negs)
        neg_crops = _Crops(nc.images, (0, 0, window[1], window[0]), nc.sources)
        if d.mirror_negatives:
            neg_crops = _concat([neg_crops, _mirrored(neg_crops)])
    images: list[torch.Tensor] = []
    sources: list[str] = []
    if d.negative_images:
        paths, sk = _image_paths(d.negative_images, exclude)
        skipped += sk
        if not paths:
            raise DataError(f"no negative images found in {d.negative_images}")
        arrs, sources, sk = load_images(paths, strict=d.strict, colour=colour)
        skipped += sk
        for a in arrs:
            t = torch.from_numpy(a)
            images.append(t.permute(2, 0, 1).contiguous() if t.ndim == 3 else t[None])
        if d.gray_copies and colour:  # gray copies: a colour model that also works on gray
            images += [_gray(im[None])[0] for im in images]
            sources = sources + [s + "#gray" for s in sources]
        if d.blur_copies > 0:  # the backgrounds blurred too: blur alone is no person
            pick = _blur_pick(len(images), float(d.blur_share), int(cfg.seed) + 13)
            images += [_blurred(images[i][None], float(d.blur_copies))[0] for i in pick]
            sources = sources + [sources[i] + "#blur" for i in pick]
        if d.mirror_negatives:  # mirrored images: twice the backgrounds to sample and mine
            images += [im.flip(-1) for im in images]
            sources = sources + [s + "#flip" for s in sources]
    return ChannelData(positives, neg_crops, images, sources, skipped)


def _group_key(source: str) -> str:
    return source.split("#", 1)[0].split("@", 1)[0]


def _split_groups(keys: list[str], fraction: float, gen: torch.Generator) -> set[str]:
    uniq = sorted(set(keys))
    perm = torch.randperm(len(uniq), generator=gen).tolist()
    n_out = round(fraction * len(uniq))
    if len(uniq) >= 2:
        n_out = min(max(n_out, 1), len(uniq) - 1)
    return {uniq[i] for i in perm[:n_out]}


def _stage_trees(cfg: TrainConfig, r: int) -> int:
    rounds = cfg.mining.rounds
    return max(32, cfg.learn.n_trees // 4 ** (rounds - r)) if r < rounds else cfg.learn.n_trees


def held_out_cascade_threshold(
    staged_pos: torch.Tensor, keep: torch.Tensor, *, miss: float, upper: float
) -> float:
    """The constant soft-cascade threshold set from held-out positives (``learn.cascade =
    "held-out"``): the ``miss`` quantile of the lowest running margins of the positives
    ``keep`` (those the calibration finds confident), a hair below it so that at most that
    share of them is rejected, and never above ``upper``.

    Args:
        staged_pos: ``(n, R)`` running margins of the held-out positives after each tree.
        keep: ``(n,)`` bool, the positives the cascade must keep.

    Returns:
        The threshold (``upper`` when ``keep`` selects none).
    """
    keep = torch.as_tensor(keep, dtype=torch.bool).reshape(-1)
    if not bool(keep.any()):
        return float(upper)
    low = staged_pos[keep].to(torch.float64).min(1).values
    q = torch.quantile(low, float(miss), interpolation="lower") if miss > 0 else low.min()
    q = float(q)
    return min(float(upper), q - 1e-5 * (1.0 + abs(q)))


def mine_windows(
    det: Detector,
    images: list[torch.Tensor],
    sources: list[str],
    *,
    margin: float,
    scale_step: float,
    stride: float,
    min_scale: float,
    max_scale: float | None,
) -> tuple[list[tuple[float, int, list[float]]], int, int]:
    """Scan object-free images with ``det`` (its soft cascade as set) and return the windows
    scoring at least ``margin`` as ``(margin, image, box)``, the number of windows scanned and
    the number scoring at least 0 (false positives at the decision boundary)."""
    from torchtrack.detect.scan import scan_batch, scan_window_count

    found: list[tuple[float, int, list[float]]] = []
    scanned = fp = 0
    for i, img in enumerate(images):
        h, w = img.shape[-2:]
        if h < det.window[0] * min_scale or w < det.window[1] * min_scale:
            continue
        kw = {
            "scale_step": scale_step,
            "stride": stride,
            "min_scale": min_scale,
            "max_scale": max_scale,
        }
        boxes, m = scan_batch(det, img[None], threshold=margin, margin=True, nms_iou=None, **kw)[0]
        scanned += scan_window_count(det, (h, w), **kw)
        fp += int((m >= 0).sum())
        found += [(float(v), i, b) for v, b in zip(m.tolist(), boxes.tolist(), strict=True)]
    return found, scanned, fp


def train_channel_detector(
    cfg: TrainConfig,
    *,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
    force: bool = False,
) -> Detector:
    """Train, mine, calibrate and cascade a channel-feature detector (see the module notes).

    Args:
        cfg: a validated config with ``features.kind = "channels"``.
        progress: progress bars.
        log: called with one line per step (a false-positive rate mining did not reach is
            the ``TrainingWarning`` below, not a line too: the CLI prints both).
        force: train even on too little data (the minimums of
            :func:`~torchtrack.detect.training.check_data_sizes`; the reasons are logged and
            recorded in the summary as ``forced``).

    Returns:
        a calibrated :class:`Detector` whose bank holds only the features its trees use.

    Raises:
        DataError / ConfigError: unusable data or configuration.

    Warns:
        TrainingWarning: mining ended with a false-positive rate on the training images above
            ``mining.target_fpr``.
    """
    from torchtrack.detect.training import (
        _data_root,
        _relative_to,
        check_data_sizes,
        portable_config,
    )
    from torchtrack.learn import calibration_metrics, make_calibrator
    from torchtrack.learn.trees import BoostedTrees, code_features, quantile_edges

    log = log or (lambda _s: None)
    cfg.validate()
    if cfg.features.kind != "channels" or cfg.classifier() != "trees":
        raise ConfigError("train_channel_detector needs features.kind = 'channels' and trees")
    t_start = time.perf_counter()
    gen = torch.Generator().manual_seed(int(cfg.seed))
    window = (int(cfg.window[0]), int(cfg.window[1]))
    f, lr, mi, d = cfg.features, cfg.learn, cfg.mining, cfg.data
    pool = channel_bank(
        window,
        f.channel_set(),
        cell=f.cell,
        cells=f.cells,
        boxes=f.boxes,
        haar=f.haar,
        seed=int(cfg.seed),
    )
    data = load_channel_data(cfg, progress=progress)
    n_img = len(data.images)
    log(
        f"data: {len(data.positives[0])} positive crops x {len(data.positives)} scale(s), "
        f"{len(data.negative_crops) if data.negative_crops else 0} negative crops, {n_img} "
        f"negative images, {len(data.skipped)} file(s) skipped; pool {len(pool)} features over "
        f"{len(pool.channels)} channels {list(pool.channels.channels)}"
    )
    for path, why in data.skipped[:20]:
        log(f"  skipped {path}: {why}")
    # random windows of the negative images, then the calibration split by source group
    rand = WindowSet(
        data.images, torch.zeros(0, dtype=torch.long), torch.zeros((0, 4), dtype=torch.float64), []
    )
    if n_img and d.random_negatives > 0:
        picks = sample_boxes(
            [tuple(im.shape[-2:]) for im in data.images],
            window,
            d.random_negatives,
            min_scale=d.negative_min_scale,
            max_scale=d.negative_max_scale,
            generator=gen,
        )
        rand = WindowSet(
            data.images,
            torch.tensor([p[0] for p in picks], dtype=torch.long),
            torch.tensor([p[1:] for p in picks], dtype=torch.float64),
            [f"{data.image_sources[p[0]]}@{p[1]},{p[2]},{p[3]},{p[4]}" for p in picks],
        )
    frac = lr.calibration_fraction
    pos_keys = [_group_key(s) for s in data.positives[0].sources]
    held_pos = _split_groups(pos_keys, frac, gen)
    neg_sources = (data.negative_crops.sources if data.negative_crops else []) + rand.sources
    if not neg_sources:
        raise DataError("no negative crops or windows to train on")
    held_neg = _split_groups([_group_key(s) for s in neg_sources], frac, gen)

    def side(sources: list[str], held: set[str]) -> tuple[torch.Tensor, torch.Tensor]:
        out = torch.tensor([_group_key(s) in held for s in sources], dtype=torch.bool)
        idx = torch.arange(len(sources))
        return idx[~out], idx[out]

    pos_tr, pos_ca = [], []
    for crops in data.positives:
        a, b = side(crops.sources, held_pos)
        pos_tr.append(_Crops(crops.images[a], crops.region, [crops.sources[i] for i in a.tolist()]))
        pos_ca.append(_Crops(crops.images[b], crops.region, [crops.sources[i] for i in b.tolist()]))
    nc_tr = nc_ca = None
    if data.negative_crops is not None:
        a, b = side(data.negative_crops.sources, held_neg)
        nc = data.negative_crops
        nc_tr = _Crops(nc.images[a], nc.region, [nc.sources[i] for i in a.tolist()])
        nc_ca = _Crops(nc.images[b], nc.region, [nc.sources[i] for i in b.tolist()])
    ra, rb = side(rand.sources, held_neg)
    rand_tr, rand_ca = rand.subset(ra), rand.subset(rb)
    mine_imgs = [i for i, s in enumerate(data.image_sources) if _group_key(s) not in held_neg]
    n_pos_tr = sum(len(c) for c in pos_tr)
    n_pos_ca = sum(len(c) for c in pos_ca)
    n_neg_tr = (len(nc_tr) if nc_tr else 0) + len(rand_tr)
    n_neg_ca = (len(nc_ca) if nc_ca else 0) + len(rand_ca)
    if min(n_pos_tr, n_pos_ca, n_neg_tr, n_neg_ca) == 0:
        raise DataError(
            "too few crops to hold out a calibration set: need at least two source files per class"
        )
    log(
        f"split: train {n_pos_tr} pos / {n_neg_tr} neg, calibration {n_pos_ca} pos / {n_neg_ca} "
        f"neg; {len(mine_imgs)} of {n_img} negative images mined"
    )
    too_little = check_data_sizes(
        cfg,
        pos_tr[0].images,
        torch.empty((n_neg_tr, 1, 1, 1)),
        pos_ca[0].images,
        torch.empty((n_neg_ca, 1, 1, 1)),
    )
    if too_little and not force:
        raise DataError(
            "too little data to train a detector: "
            + "; ".join(too_little)
            + f" (calibration hold-out {frac:.0%}). Add crops, lower learn.min_train_per_class / "
            "learn.min_calibration_per_class, or train anyway with --force (force=True)"
        )
    for line in too_little:
        log(f"  warning (forced): {line}")
    # features of the whole pool, coded once
    t0 = time.perf_counter()
    xs = [_crop_features(c, pool) for c in pos_tr]
    if nc_tr is not None:
        xs.append(_crop_features(nc_tr, pool))
    xs.append(channel_window_features(rand_tr, pool))
    x = torch.cat(xs)
    del xs
    y = torch.cat((torch.ones(n_pos_tr), torch.zeros(n_neg_tr))).long()
    edges = quantile_edges(x, 256)
    codes = code_features(x, edges)
    del x
    t_feat = time.perf_counter() - t0
    log(
        f"features: {codes.shape[1]} windows x {codes.shape[0]} = {codes.numel() / 2**20:.0f} MiB codes ({t_feat:.1f} s)"
    )
    rounds: list[dict[str, Any]] = []
    hard = 0
    clf = None
    target_met = False
    r = 0
    while True:
        final = r >= mi.rounds or target_met
        n_trees = cfg.learn.n_trees if final else _stage_trees(cfg, r)
        t0 = time.perf_counter()
        clf = BoostedTrees(
            n_estimators=n_trees,
            max_depth=lr.tree_depth,
            variant=cfg.variant(),
            feature_fraction=lr.feature_fraction,
            weight_trimming=lr.weight_trimming,
        )
        prev = torch.get_num_threads()
        torch.set_num_threads(1)  # many small scatter_add_ calls: threads only contend
        try:
            clf.fit_codes(
                codes,
                edges,
                y,
                generator=torch.Generator().manual_seed(int(cfg.seed) + r),
                progress=progress,
            )
        finally:
            torch.set_num_threads(prev)
        t_fit = time.perf_counter() - t0
        entry: dict[str, Any] = {
            "round": r,
            "trees": n_trees,
            "negatives": int((y == 0).sum()),
            "fit_s": t_fit,
        }
        log(
            f"round {r}: {n_trees} trees on {int((y == 1).sum())} pos / {int((y == 0).sum())} neg ({t_fit:.1f} s)"
        )
        # scan the training images: hard negatives (and the false-positive rate)
        t0 = time.perf_counter()
        clf.reject_ = torch.full_like(clf.reject_, float(mi.margin))  # constant soft cascade
        det = Detector(pool, torch.arange(len(pool)), clf, None, name=cfg.name)
        found, scanned, fp = mine_windows(
            det,
            [data.images[i] for i in mine_imgs],
            [data.image_sources[i] for i in mine_imgs],
            margin=mi.margin,
            scale_step=mi.scale_step,
            stride=mi.stride,
            min_scale=mi.min_scale if mi.min_scale is not None else d.negative_min_scale,
            max_scale=mi.max_scale,
        )
        fpr = fp / max(scanned, 1)
        entry.update({"scanned_windows": scanned, "false_positives": fp, "fpr": fpr})
        target_met = fpr <= mi.target_fpr
        if final:
            entry["mine_s"] = time.perf_counter() - t0
            rounds.append(entry)
            log(f"  training images: {fp} false positives in {scanned} windows (FPR {fpr:.2e})")
            break
        # the highest-scoring windows, no image more than twice its share
        found.sort(key=lambda c: -c[0])
        cap = max(1, math.ceil(2 * mi.per_round / max(len(mine_imgs), 1)))
        per_img: dict[int, int] = {}
        picked = []
        for _v, i, b in found:
            if per_img.get(i, 0) < cap:
                per_img[i] = per_img.get(i, 0) + 1
                picked.append((i, b))
            if len(picked) >= mi.per_round:
                break
        if picked:
            ws = WindowSet(
                [data.images[mine_imgs[i]] for i in range(len(mine_imgs))],
                torch.tensor([i for i, _ in picked], dtype=torch.long),
                torch.tensor([b for _, b in picked], dtype=torch.float64),
                [],
            )
            codes = torch.cat((codes, code_features(channel_window_features(ws, pool), edges)), 1)
            y = torch.cat((y, torch.zeros(len(picked), dtype=torch.long)))
            hard += len(picked)
        entry.update({"mined": len(picked), "mine_s": time.perf_counter() - t0})
        rounds.append(entry)
        log(
            f"  mining: {fp} false positives in {scanned} windows (FPR {fpr:.2e}); "
            f"+{len(picked)} hard negatives ({entry['mine_s']:.1f} s)"
        )
        if target_met:
            log(f"  FPR at or below mining.target_fpr {mi.target_fpr:g}: no more mining rounds")
        r += 1
    if not target_met:
        msg = (
            f"detector {cfg.name!r}: after {len(rounds) - 1} mining round(s) the training "
            f"negative images still give a false-positive rate of {rounds[-1]['fpr']:.2e} "
            f"(windows with margin >= 0), above mining.target_fpr = {mi.target_fpr:g}; add "
            "negative images or mining rounds, or raise target_fpr"
        )
        # warned only, not logged as well: ``torchtrack train`` prints both channels, so the
        # user read it twice; a warning reaches a caller who passes no ``log`` (Python shows
        # it), can be filtered or recorded, and shows under --quiet
        warnings.warn(msg, TrainingWarning, stacklevel=2)
    # keep the used features only
    used = torch.unique(clf.feature_)
    remap = torch.full((len(pool),), -1, dtype=torch.long)
    remap[used] = torch.arange(used.numel())
    clf.feature_ = remap[clf.feature_]
    clf.n_features_in_ = int(used.numel())
    bank = pool.subset(used)
    index = torch.arange(used.numel())
    # calibration on the held-out windows
    xp = torch.cat([_crop_features(c, bank) for c in pos_ca])
    xn_parts = [_crop_features(nc_ca, bank)] if nc_ca is not None else []
    xn_parts.append(channel_window_features(rand_ca, bank))
    xn = torch.cat(xn_parts)
    m_ca = torch.cat((clf.decision_function(xp), clf.decision_function(xn))).double()
    y_ca = torch.cat((torch.ones(xp.shape[0]), torch.zeros(xn.shape[0])))
    calibrator = make_calibrator(lr.calibration).fit(m_ca, y_ca.long())
    cal_metrics = calibration_metrics(calibrator.predict_proba(m_ca), y_ca.long())
    dr, _, _ = detection_rate_at_fpr(m_ca, y_ca, 0.01)
    auc = roc_auc(m_ca, y_ca)
    # the tracking head: the first trees, calibrated on the same held-out windows
    head = None
    head_summary: dict[str, Any] = {}
    # running margins of the held-out windows, (n, R): the head's and the cascade's statistics
    staged_p = clf.staged_decision_function(xp)
    staged_n = clf.staged_decision_function(xn)
    staged = torch.cat((staged_p, staged_n)).double()
    for k in sorted({32, 64, 128, 256, int(lr.tracking_trees)} - {0}):
        if k > staged.shape[1]:
            continue
        mk = staged[:, k - 1]
        cal_k = make_calibrator("platt").fit(mk, y_ca.long())
        met_k = calibration_metrics(cal_k.predict_proba(mk), y_ca.long())
        dr_k, _, _ = detection_rate_at_fpr(mk, y_ca, 0.01)
        head_summary[str(k)] = {
            "auc": roc_auc(mk, y_ca),
            "dr_at_1pct_fpr": dr_k,
            "features": int(torch.unique(clf.feature_[:k]).numel()),
            "ece": float(met_k["ece"]),
        }
        if k == lr.tracking_trees and k < staged.shape[1]:
            head = (k, cal_k)
    if head is not None:
        h = head_summary[str(head[0])]
        log(
            f"tracking head: first {head[0]} trees ({h['features']} features), held-out "
            f"detection rate {h['dr_at_1pct_fpr']:.3f} at 1% FPR, AUC {h['auc']:.4f}, "
            f"ECE {h['ece']:.4f}"
        )
    # the soft cascade the scans use
    cascade: dict[str, Any] = {"method": lr.cascade}
    big = float(torch.finfo(torch.float32).max)
    clf.reject_ = torch.full_like(clf.reject_, -big)
    # the held-out positives a cascade must keep: those the calibration finds confident
    mp = m_ca[: xp.shape[0]]
    confident = calibrator.predict_proba(mp) >= float(lr.cascade_probability)
    if lr.cascade == "constant":
        clf.reject_ = torch.full_like(clf.reject_, float(lr.cascade_threshold))
        cascade["threshold"] = float(lr.cascade_threshold)
    elif lr.cascade == "held-out":
        theta = held_out_cascade_threshold(
            staged_p, confident, miss=float(lr.cascade_miss), upper=float(lr.cascade_threshold)
        )
        clf.reject_ = torch.full_like(clf.reject_, theta)
        cascade.update(
            {
                "threshold": theta,
                "upper": float(lr.cascade_threshold),
                "probability": float(lr.cascade_probability),
                "miss": float(lr.cascade_miss),
            }
        )
    elif lr.cascade == "backward" and lr.cascade_probability > 0:
        c = float(lr.cascade_probability)
        cascade.update({"probability": c, "miss": float(lr.cascade_miss)})
        if bool(confident.any()):
            m_cut = float(mp[confident].min())
            clf.fit_cascade(xp, m_cut, quantile=float(lr.cascade_miss))
            cascade.update(
                {
                    "min_margin": m_cut,
                    "positives_kept": int(confident.sum()),
                    "positives": int(mp.numel()),
                }
            )
    # share of held-out positives and negatives the cascade stops before the last tree
    rej = clf.reject_.to(staged_p.dtype)
    cascade["held_out_positives_rejected"] = float((staged_p < rej).any(1).double().mean())
    if bool(confident.any()):
        cascade["held_out_confident_positives_rejected"] = float(
            (staged_p[confident] < rej).any(1).double().mean()
        )
    cascade["held_out_negatives_rejected"] = float((staged_n < rej).any(1).double().mean())
    log(
        f"held-out: detection rate {dr:.3f} at 1% FPR, AUC {auc:.4f}; {lr.calibration} NLL "
        f"{cal_metrics['nll']:.4f}, ECE {cal_metrics['ece']:.4f}; {used.numel()} of {len(pool)} "
        "features used"
    )
    root = _data_root(cfg)
    summary: dict[str, Any] = {
        "config": portable_config(cfg),
        "counts": {
            "positives_train": n_pos_tr,
            "negatives_train": int((y == 0).sum()),
            "positives_calibration": n_pos_ca,
            "negatives_calibration": n_neg_ca,
            "hard_negatives": hard,
            "skipped_files": len(data.skipped),
            "negative_images": n_img,
            "mined_images": len(mine_imgs),
        },
        "features": {
            "pool": len(pool),
            "used": int(used.numel()),
            "channels": list(pool.channels.channels),
        },
        "calibration_sources": sorted(_relative_to(k, root) for k in held_pos | held_neg),
        "excluded_lists": [Path(p).name for p in d.exclude],
        "rounds": rounds,
        "cascade": cascade,
        "held_out": {
            "set": "calibration hold-out (never used to train the classifier)",
            "auc": auc,
            "dr_at_1pct_fpr": dr,
            "calibrated_in_sample": {k: float(v) for k, v in cal_metrics.items()},
        },
        "tracking_head": {"trees": lr.tracking_trees, "held_out_by_trees": head_summary},
        "features_s": t_feat,
        "train_seconds": time.perf_counter() - t_start,
    }
    if too_little:
        summary["forced"] = too_little
    det = Detector(
        bank,
        index,
        clf,
        calibrator,
        name=cfg.name,
        summary=summary,
        object_box=cfg.object_box(),
        tracking_head=head,
    )
    if lr.box_regression:
        det = fit_box_regression(cfg, det, progress=progress)
    return det


def fit_box_regression(cfg: TrainConfig, det: Detector, *, progress: bool = False) -> Detector:
    """``det`` with a box regressor fitted on ``cfg``'s positive crops (their windows in
    context, ``data.region``, and their mirror images when the region is centred; the
    config's ``data.exclude`` lists left out), seeded by ``cfg.seed``: what
    ``learn.box_regression`` adds at the end of training, and what
    ``train/default_models.py --box-regression`` adds to a trained model.

    Raises:
        DataError: fewer than 8 positive crops.
    """
    from torchtrack.detect.box_regression import fit_box_regressor

    _, crops = _positive_crops(cfg, excluded_names(cfg.data), det.colour, progress)
    mirror = _mirrored(crops)
    if cfg.data.mirror_positives and mirror.region == crops.region:  # a centred window
        crops = _concat([crops, mirror])
    groups = [_group_key(s) for s in crops.sources]
    reg = fit_box_regressor(
        det,
        crops.images,
        crops.region,
        groups,
        seed=int(cfg.seed),
        scales=tuple(dict.fromkeys(float(q) for q in cfg.data.positive_scales)),
    )
    return replace(det, box_regressor=reg)
