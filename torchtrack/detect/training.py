"""Training a calibrated class detector from crops (Chateau et al. 2006, sections 2.4, 3, 4.1).

:func:`train_detector` trains the configured kind: ``features.kind = "channels"`` goes to
:mod:`torchtrack.detect.train_channels` (integral channel features, boosted trees, mining
rounds, soft cascade); ``"haar"`` (the paper setting) follows the steps below.

Steps of the Haar path:

1. Load positive crops (plus mirror images), negative crops and random windows of negative
   images; names listed in ``data.exclude`` (the held-out test split) are never read.
2. Hold out ``learn.calibration_fraction`` (paper: 30%) of the crops for calibration,
   stratified by class and grouped by source image, so a crop and its mirror image always fall
   on the same side.
3. Compute the full Haar bank on the training crops (one ``(n, F)`` float32 matrix, built in
   chunks), select ``learn.n_features`` features by AdaBoost, train the classifier (boosted
   stumps or an SVM) on them.
4. Optional hard-negative mining: scan the negative images, add the highest-scoring windows to
   the training negatives, go back to 3.
5. Fit the calibrator (Platt or isotonic) on the held-out margins; record counts, the split and
   the held-out metrics in the detector's summary.

**Too little data is refused** (:func:`check_data_sizes`), before any feature is computed:
fewer than ``learn.min_train_per_class`` training crops (default 20) or
``learn.min_calibration_per_class`` held-out crops (default 10) in a class, or positives of
which more than half are flat (no contrast: every Haar feature is 0 on them). ``force=True``
(``torchtrack train --force``) trains anyway and records the reasons in the summary
(``forced``). A calibration whose probability falls as the margin rises (the classifier is
worse than chance on the held-out crops) is always refused: such a model cannot be saved.
"""

from __future__ import annotations

import gc
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from torchtrack.detect.config import TrainConfig, excluded_names
from torchtrack.detect.detector import Detector
from torchtrack.detect.evaluate import crop_scores, detection_rate_at_fpr, roc_auc
from torchtrack.detect.scan import sliding_windows
from torchtrack.errors import ConfigError, DataError
from torchtrack.features.haar import HaarBank, haar_bank, haar_features_dense, integrals
from torchtrack.io.crops import (
    CropSet,
    crops_from_boxes,
    list_image_files,
    load_crops,
    load_images,
    mirror,
    sample_windows,
)

__all__ = [
    "TrainingData",
    "check_data_sizes",
    "group_split",
    "load_training_data",
    "mine_hard_negatives",
    "portable_config",
    "train_detector",
]


@dataclass
class TrainingData:
    """Crops for one training run.

    Attributes:
        positives, negatives: window-sized crops (negatives include random windows).
        images: grayscale negative images (for mining), with ``image_sources``.
        skipped: ``(path, reason)`` of every unusable file.
    """

    positives: CropSet
    negatives: CropSet
    images: list[np.ndarray]
    image_sources: list[str]
    skipped: list[tuple[str, str]]


def _folder_pattern(entry: str) -> tuple[str, str | None]:
    """``"dir/pos-*.pgm"`` -> ``("dir", "pos-*.pgm")``; a plain folder has no pattern."""
    p = Path(entry)
    if any(c in p.name for c in "*?["):
        return str(p.parent), p.name
    return entry, None


def _image_paths(entries: list[str], exclude: set[str]) -> tuple[list[Path], list[tuple[str, str]]]:
    paths, skipped = [], []
    for e in entries:
        p = Path(e)
        if p.is_dir():
            files, sk = list_image_files(p)
            skipped += sk
            paths += [f for f in files if f.name not in exclude]
        elif p.is_file():
            if p.name not in exclude:
                paths.append(p)
        else:
            raise DataError(f"negative image path {e!r} does not exist")
    return paths, skipped


def load_training_data(
    cfg: TrainConfig, *, generator: torch.Generator | None = None, progress: bool = False
) -> TrainingData:
    """Read every crop and negative image named by ``cfg.data`` (see the module notes).

    Raises:
        DataError: a missing or empty folder; with ``data.strict``, any unusable file.
    """
    d = cfg.data
    window = (int(cfg.window[0]), int(cfg.window[1]))
    exclude = excluded_names(d)
    region = tuple(d.region) if d.region is not None else None
    crop_size = tuple(d.crop_size) if d.crop_size is not None else None
    pos = CropSet.concat(
        [
            load_crops(
                folder,
                window,
                region=region,
                crop_size=crop_size,
                exclude=exclude,
                pattern=pat,
                strict=d.strict,
                progress=progress,
            )
            for folder, pat in map(_folder_pattern, d.positives)
        ]
    )
    if d.mirror_positives:
        pos = mirror(pos)
    negs = [
        load_crops(folder, window, exclude=exclude, pattern=pat, strict=d.strict, progress=progress)
        for folder, pat in map(_folder_pattern, d.negatives)
    ]
    skipped = list(pos.skipped) + [s for n in negs for s in n.skipped]
    if d.mirror_negatives:
        negs = [mirror(n) for n in negs]
    images: list[np.ndarray] = []
    sources: list[str] = []
    if d.negative_images:
        paths, sk = _image_paths(d.negative_images, exclude)
        skipped += sk
        if not paths:
            raise DataError(f"no negative images found in {d.negative_images}")
        images, sources, sk = load_images(paths, strict=d.strict)
        skipped += sk
        if d.random_negatives > 0:
            negs.append(
                sample_windows(
                    images,
                    sources,
                    window,
                    d.random_negatives,
                    min_scale=d.negative_min_scale,
                    max_scale=d.negative_max_scale,
                    generator=generator,
                )
            )
    if not negs:
        raise DataError("no negative crops or windows to train on")
    neg = CropSet.concat(negs)
    return TrainingData(pos, neg, images, sources, skipped)


def _group_key(source: str) -> str:
    """Crops from one file (the crop, its mirror, windows of one image) share a group."""
    return source.split("#", 1)[0].split("@", 1)[0]


def group_split(
    sources: list[str], fraction: float, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Split rows into (keep, held_out) so that ``fraction`` of the *groups* (source files) is
    held out; rows of one group never straddle the split.

    Returns:
        two sorted int64 index tensors.
    """
    keys = [_group_key(s) for s in sources]
    uniq = sorted(set(keys))
    perm = torch.randperm(len(uniq), generator=generator).tolist()
    n_out = round(fraction * len(uniq))
    if len(uniq) >= 2:
        n_out = min(max(n_out, 1), len(uniq) - 1)
    held = {uniq[i] for i in perm[:n_out]}
    out = torch.tensor([k in held for k in keys], dtype=torch.bool)
    idx = torch.arange(len(keys))
    return idx[~out], idx[out]


def _data_root(cfg: TrainConfig) -> str | None:
    """The deepest folder holding every data entry of ``cfg.data`` (None without entries)."""
    d = cfg.data
    entries = [str(p) for p in (*d.positives, *d.negatives, *d.negative_images)]
    if not entries:
        return None
    return os.path.commonpath([os.path.dirname(os.path.abspath(p)) for p in entries])


def _relative_to(path: str, root: str | None) -> str:
    if root is None or not os.path.isabs(path):
        return path
    return Path(os.path.relpath(path, root)).as_posix()


def portable_config(cfg: TrainConfig) -> dict[str, Any]:
    """``cfg.to_dict()`` without this machine's absolute paths (for the model's summary).

    The data entries (``positives``, ``negatives``, ``negative_images``) become relative to the
    data root, the deepest folder that holds all of them (for the shipped configs
    ``detection_crops``), recorded by name as ``data.root``; the ``exclude`` lists are recorded
    by file name (they live in ``configs/splits``).
    """
    out = cfg.to_dict()
    d = out["data"]
    root = _data_root(cfg)
    if root is not None:
        for k in ("positives", "negatives", "negative_images"):
            d[k] = [_relative_to(os.path.abspath(p), root) for p in d[k]]
        d["root"] = Path(root).name
    d["exclude"] = [Path(p).name for p in d["exclude"]]
    return out


def check_data_sizes(
    cfg: TrainConfig,
    pos_train: torch.Tensor,
    neg_train: torch.Tensor,
    pos_cal: torch.Tensor,
    neg_cal: torch.Tensor,
) -> list[str]:
    """Why the data are too few (or unusable) to train on: an empty list when they are fine.

    Args:
        cfg: the training config (its ``learn.min_*`` minimums and ``features.min_std``).
        pos_train, neg_train, pos_cal, neg_cal: ``(n, 1, H, W)`` uint8 crops of each part.
    """
    lr = cfg.learn
    why = []
    for what, n, lo in (
        ("positive training crops", pos_train.shape[0], lr.min_train_per_class),
        ("negative training crops", neg_train.shape[0], lr.min_train_per_class),
        ("positive calibration crops", pos_cal.shape[0], lr.min_calibration_per_class),
        ("negative calibration crops", neg_cal.shape[0], lr.min_calibration_per_class),
    ):
        if n < lo:
            why.append(f"{n} {what}, fewer than the minimum {lo}")
    pos = torch.cat((pos_train, pos_cal))
    if pos.shape[0]:
        std = pos.flatten(1).to(torch.float32).std(1, unbiased=False)
        flat = int((std < cfg.features.min_std).sum())
        if 2 * flat > pos.shape[0]:
            why.append(
                f"{flat} of {pos.shape[0]} positive crops are flat (intensity std below "
                f"{cfg.features.min_std}): every Haar feature is 0 on them"
            )
    return why


def _whole_boxes(n: int, window: tuple[int, int]) -> torch.Tensor:
    return torch.tensor([0.0, 0.0, float(window[1]), float(window[0])]).expand(n, 1, 4)


def _fit_classifier(
    cfg: TrainConfig, bank: HaarBank, pos: torch.Tensor, neg: torch.Tensor, progress: bool, log
) -> tuple[torch.Tensor, Any, dict[str, float]]:
    from torchtrack.learn import BoostedStumps, SVMClassifier, select_features

    lr = cfg.learn
    crops = torch.cat((pos, neg))
    y = torch.cat((torch.ones(pos.shape[0]), torch.zeros(neg.shape[0]))).long()
    t0 = time.perf_counter()
    x = haar_features_dense(crops, bank)  # (n, F) float32
    t1 = time.perf_counter()
    log(
        f"  features: {x.shape[0]} crops x {x.shape[1]} = {x.numel() * 4 / 2**30:.2f} GiB ({t1 - t0:.1f} s)"
    )
    idx = select_features(x, y, lr.n_features, n_bins=lr.selection_bins, progress=progress)
    t2 = time.perf_counter()
    xs = x[:, idx].contiguous()
    del x
    gc.collect()
    if cfg.classifier() == "adaboost":
        clf = BoostedStumps(n_estimators=lr.n_estimators or lr.n_features, variant=cfg.variant())
    else:
        clf = SVMClassifier(kernel=lr.svm_kernel, C=lr.svm_c)
    clf.fit(xs, y)
    t3 = time.perf_counter()
    log(f"  selection {t2 - t1:.1f} s, {cfg.classifier()} {t3 - t2:.1f} s")
    times = {"features_s": t1 - t0, "selection_s": t2 - t1, "classifier_s": t3 - t2}
    return idx, clf, times


def mine_hard_negatives(
    det: Detector,
    images: list[np.ndarray],
    sources: list[str],
    n: int,
    *,
    scale_step: float = 1.2,
    stride: float = 0.1,
    max_scale: float | None = None,
) -> CropSet:
    """The ``n`` highest-margin windows of object-free images (false positives to learn from).

    Every image is scanned at all scales that fit; windows are cut out and resized to the
    detector window (area averaging).
    """
    cand: list[tuple[float, int, list[float]]] = []
    for i, img in enumerate(images):
        boxes = sliding_windows(
            img.shape, det.window, scale_step=scale_step, stride=stride, max_scale=max_scale
        )
        if boxes.shape[0] == 0:
            continue
        frame = torch.from_numpy(img)[None, None]
        m = det.decision_function(integrals(frame), boxes[None])[0]
        k = min(n, m.numel())
        top = m.topk(k)
        cand += [
            (float(v), i, boxes[j].tolist()) for v, j in zip(top.values, top.indices, strict=True)
        ]
    cand.sort(key=lambda c: -c[0])
    cand = cand[:n]
    out = np.empty((len(cand), det.window[0], det.window[1]), dtype=np.uint8)
    srcs = []
    for r, (_, i, box) in enumerate(cand):
        out[r] = crops_from_boxes(images[i], np.array([box]), det.window)[0]
        x, y, w, h = (round(v, 1) for v in box)
        srcs.append(f"{sources[i]}@{x},{y},{w},{h}")
    return CropSet(torch.from_numpy(out)[:, None], srcs)


def train_detector(
    cfg: TrainConfig,
    *,
    progress: bool = False,
    log: Callable[[str], None] | None = None,
    force: bool = False,
) -> Detector:
    """Train, mine and calibrate a detector as configured (see the module notes).

    Args:
        cfg: a validated :class:`~torchtrack.detect.config.TrainConfig`.
        progress: show progress bars.
        log: called with one line per step (default: silent).
        force: train even on too little data (:func:`check_data_sizes`; the reasons are
            logged and recorded in the summary as ``forced``).

    Returns:
        a calibrated :class:`Detector` whose ``summary`` records data counts, the held-out
        split, timings and held-out metrics.

    Raises:
        DataError: unusable or too little data (without ``force``), or a calibration whose
            probability falls as the margin rises.
        ConfigError: an invalid configuration.
    """
    from torchtrack.learn import calibration_metrics, make_calibrator

    log = log or (lambda _s: None)
    cfg.validate()
    if cfg.features.kind == "channels":
        from torchtrack.detect.train_channels import train_channel_detector

        return train_channel_detector(cfg, progress=progress, log=log, force=force)
    gen = torch.Generator().manual_seed(int(cfg.seed))
    window = (int(cfg.window[0]), int(cfg.window[1]))
    f = cfg.features
    bank = haar_bank(
        window,
        n_scales=f.n_scales,
        sizes=tuple(f.sizes) if f.sizes else None,
        stride=f.stride,
        min_std=f.min_std,
    )
    if cfg.learn.n_features > len(bank):  # was refused after every crop's features were computed
        raise ConfigError(
            f"learn.n_features (--features) is {cfg.learn.n_features}, more than the "
            f"{len(bank)} features of the {window[0]}x{window[1]} window's Haar bank"
        )
    t_start = time.perf_counter()
    data = load_training_data(cfg, generator=gen, progress=progress)
    log(
        f"data: {len(data.positives)} positive and {len(data.negatives)} negative crops, "
        f"{len(data.images)} negative images, {len(data.skipped)} file(s) skipped"
    )
    for path, why in data.skipped[:20]:
        log(f"  skipped {path}: {why}")
    frac = cfg.learn.calibration_fraction
    p_tr, p_ca = group_split(data.positives.sources, frac, gen)
    n_tr, n_ca = group_split(data.negatives.sources, frac, gen)
    if min(p_tr.numel(), p_ca.numel(), n_tr.numel(), n_ca.numel()) == 0:
        raise DataError(
            "too few crops to hold out a calibration set: need at least two source files per class"
        )
    pos_tr, pos_ca = data.positives.images[p_tr], data.positives.images[p_ca]
    neg_tr, neg_ca = data.negatives.images[n_tr], data.negatives.images[n_ca]
    log(
        f"split: train {pos_tr.shape[0]} pos / {neg_tr.shape[0]} neg, calibration "
        f"{pos_ca.shape[0]} pos / {neg_ca.shape[0]} neg"
    )
    too_little = check_data_sizes(cfg, pos_tr, neg_tr, pos_ca, neg_ca)
    if too_little and not force:
        raise DataError(
            "too little data to train a detector: "
            + "; ".join(too_little)
            + f" (calibration hold-out {frac:.0%}). Add crops, lower learn.min_train_per_class / "
            "learn.min_calibration_per_class, or train anyway with --force (force=True)"
        )
    for line in too_little:
        log(f"  warning (forced): {line}")
    log(f"bank: {len(bank)} Haar features on a {window[0]}x{window[1]} window, sizes {bank.sizes}")
    rounds = []
    hard_sources: list[str] = []
    det = None
    for r in range(cfg.mining.rounds + 1):
        if r > 0:
            mined = mine_hard_negatives(
                det,
                data.images,
                data.image_sources,
                cfg.mining.per_round,
                scale_step=cfg.mining.scale_step,
                stride=cfg.mining.stride,
                max_scale=cfg.mining.max_scale,
            )
            neg_tr = torch.cat((neg_tr, mined.images))
            hard_sources += mined.sources
            log(f"mining round {r}: +{len(mined)} hard negatives -> {neg_tr.shape[0]} negatives")
        log(f"training round {r}")
        idx, clf, times = _fit_classifier(cfg, bank, pos_tr, neg_tr, progress, log)
        det = Detector(bank, idx, clf, None, name=cfg.name)
        m_ca = torch.cat((crop_scores(det, pos_ca), crop_scores(det, neg_ca)))
        y_ca = torch.cat((torch.ones(pos_ca.shape[0]), torch.zeros(neg_ca.shape[0])))
        dr, fpr, _ = detection_rate_at_fpr(m_ca, y_ca, 0.01)
        rounds.append(
            {"round": r, "negatives": int(neg_tr.shape[0]), "dr_at_1pct_fpr": dr, **times}
        )
        log(f"  held-out: detection rate {dr:.3f} at FPR {fpr:.4f}, AUC {roc_auc(m_ca, y_ca):.4f}")
    calibrator = make_calibrator(cfg.learn.calibration).fit(m_ca.double(), y_ca.long())
    if cfg.learn.calibration == "platt" and not calibrator.a_ < 0:
        raise DataError(
            f"the Platt fit on the {m_ca.numel()} held-out crops gives a probability that does not "
            f"rise with the classifier's margin (slope a = {calibrator.a_:.4g} >= 0): the "
            "classifier is no better than chance on data it was not trained on; add data or "
            "check the positive and negative folders"
        )
    p_ca_prob = calibrator.predict_proba(m_ca.double())
    cal_metrics = calibration_metrics(p_ca_prob, y_ca.long())
    summary: dict[str, Any] = {
        "config": portable_config(cfg),
        "counts": {
            "positives_train": int(pos_tr.shape[0]),
            "negatives_train": int(neg_tr.shape[0]),
            "positives_calibration": int(pos_ca.shape[0]),
            "negatives_calibration": int(neg_ca.shape[0]),
            "hard_negatives": len(hard_sources),
            "skipped_files": len(data.skipped),
            "resized_crops": data.positives.resized + data.negatives.resized,
        },
        "calibration_sources": sorted(
            _relative_to(k, _data_root(cfg))
            for k in {_group_key(data.positives.sources[i]) for i in p_ca.tolist()}
            | {_group_key(data.negatives.sources[i]) for i in n_ca.tolist()}
        ),
        "excluded_lists": [Path(p).name for p in cfg.data.exclude],
        "rounds": rounds,
        "held_out": {
            "set": "calibration hold-out (never used to train the classifier)",
            "auc": roc_auc(m_ca, y_ca),
            "dr_at_1pct_fpr": rounds[-1]["dr_at_1pct_fpr"],
            "calibrated_in_sample": {k: float(v) for k, v in cal_metrics.items()},
        },
        "train_seconds": time.perf_counter() - t_start,
    }
    if too_little:
        summary["forced"] = too_little
    log(
        f"calibration ({cfg.learn.calibration}): NLL {cal_metrics['nll']:.4f}, "
        f"ECE {cal_metrics['ece']:.4f} on {m_ca.numel()} held-out crops"
    )
    return Detector(
        bank,
        det.feature_index,
        det.classifier,
        calibrator,
        name=cfg.name,
        summary=summary,
        object_box=cfg.object_box(),
    )
