"""Training configuration of a class detector: typed dataclasses with every default in one place,
loaded from TOML (``configs/pedestrian.toml``, ``configs/vehicle.toml``) with unknown keys
rejected by name.

Paths in a TOML file are relative to the file's folder; ``$VARS`` and ``~`` are expanded
(e.g. ``"$TORCHTRACK_DATA/detection_crops/uiuc_car/CarData/TrainImages"``).
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

from torchtrack.errors import ConfigError

__all__ = [
    "DataConfig",
    "FeatureConfig",
    "LearnConfig",
    "MiningConfig",
    "TrainConfig",
    "load_train_config",
    "read_name_list",
]


#: the most random negative windows a training run may draw (each is a crop held in memory)
MAX_RANDOM_NEGATIVES = 10_000_000

#: the most hard-negative mining rounds (each scans every negative image and retrains; the
#: shipped models use 3)
MAX_MINING_ROUNDS = 100


@dataclass
class DataConfig:
    """Where the crops come from.

    Attributes:
        positives: folders of positive crops.
        negatives: folders of negative crops.
        negative_images: folders (or files) of object-free images; random windows of them are
            negatives, and hard-negative mining scans them.
        crop_size, region: ``(H0, W0)`` and ``(x, y, w, h)`` of the object inside each positive
            crop (INRIA 96x160: ``[160, 96]`` and ``[16, 16, 64, 128]``); see
            :func:`torchtrack.io.crops.load_crops`.
        object: ``(x, y, w, h)`` of the object itself inside each positive crop, in the pixels
            of ``crop_size`` (or of the window when no region is given): the detector reports
            this part of its window as the object's box (INRIA 96x160: ``[32, 32, 32, 96]``, a
            person 96 px tall with 16 px of margin on every side of the 64x128 window).
            ``None``: the object fills the window.
        positive_scales: channel features: also train on every positive crop downscaled by
            these factors (<= 1; e.g. ``[1.0, 0.5]``): the detector then sees objects at the
            resolution of people smaller than the window (the scan reads small windows from
            the frame at its own resolution). ``cell * factor`` must be a whole number.
        positive_jitter: channel models: also train on a copy of every positive crop moved by
            a random whole number of pixels up to this in x and y (the window then sits off the
            object by that much: a detector tolerant to the misaligned windows a particle filter
            scores; the crop's margin must be larger than the shift).
        gray_copies: colour channel models: also train on gray copies (R = G = B) of the
            positives and the negative images, so that the model also works on grayscale
            footage (where U = V = 0).
        blur_copies: channel models: also train on copies of the positives and the negative
            images blurred by a Gaussian of this sd in pixels (0: none): a soft lens, focus,
            compression, or a video upscaled from a smaller one, where a model that has seen
            only sharp backgrounds finds people in their blurred texture. Both sides get the
            copies, so that blur alone says nothing about the class.
        blur_share: the share of the positive crops and of the negative images (a seeded
            random pick) that get a blurred copy, in (0, 1].
        mirror_positives, mirror_negatives: add left-right mirror images (channel features:
            ``mirror_negatives`` also mirrors the negative images, for random windows and
            mining).
        random_negatives: number of random windows drawn from ``negative_images``.
        negative_min_scale, negative_max_scale: scale range of those windows (x window size).
        exclude: files listing file names (one per line, ``#`` comments) never to train or
            calibrate on: the held-out test split.
        strict: fail on unreadable files instead of skipping them.
    """

    positives: list[str] = field(default_factory=list)
    negatives: list[str] = field(default_factory=list)
    negative_images: list[str] = field(default_factory=list)
    crop_size: list[int] | None = None
    region: list[int] | None = None
    object: list[float] | None = None
    positive_scales: list[float] = field(default_factory=lambda: [1.0])
    positive_jitter: int = 0
    gray_copies: bool = False
    blur_copies: float = 0.0
    blur_share: float = 1.0
    mirror_positives: bool = True
    mirror_negatives: bool = False
    random_negatives: int = 0
    negative_min_scale: float = 1.0
    negative_max_scale: float | None = None
    exclude: list[str] = field(default_factory=list)
    strict: bool = False


@dataclass
class FeatureConfig:
    """The feature bank.

    Attributes:
        kind: ``"haar"``: Chateau et al.'s grey Haar bank with AdaBoost feature selection (the
            paper setting, see :func:`torchtrack.features.haar.haar_bank`); ``"channels"``:
            integral channel features (:func:`torchtrack.features.channels.channel_bank`).
        n_scales, sizes, stride, min_std: the Haar bank (``n_scales`` at most 8, and at most
            the halvings of the window's largest power of two down to 4 pixels; ``sizes`` left
            out or non-empty).
        channels: channel names (``L``, ``U``, ``V``, ``gray``, ``grad``, ``orient``).
        orientations, norm_radius, norm_const, gradient_lambda: see
            :class:`~torchtrack.features.channels.ChannelSet`.
        cell: lattice step in window pixels (ACF's shrink).
        cells: include every single cell of every channel.
        boxes, haar: random rectangles and random Haar filters over channels in the pool
            (each at most 1,000,000, what a channel bank holds).
    """

    kind: str = "haar"
    n_scales: int = 3
    sizes: list[int] | None = None
    stride: int = 1
    min_std: float = 1.0
    channels: list[str] = field(default_factory=lambda: ["L", "U", "V", "grad", "orient"])
    orientations: int = 6
    norm_radius: int = 5
    norm_const: float = 0.005
    gradient_lambda: float = 0.1
    cell: int = 4
    cells: bool = True
    boxes: int = 2000
    haar: int = 0

    def channel_set(self):
        """The :class:`~torchtrack.features.channels.ChannelSet` of ``channels`` (validated)."""
        from torchtrack.features.channels import ChannelSet

        return ChannelSet(
            names=tuple(self.channels) if isinstance(self.channels, list) else self.channels,
            orientations=self.orientations,
            norm_radius=self.norm_radius,
            norm_const=float(self.norm_const) if _isnum(self.norm_const) else self.norm_const,
            gradient_lambda=(
                float(self.gradient_lambda)
                if _isnum(self.gradient_lambda)
                else self.gradient_lambda
            ),
        )


@dataclass
class LearnConfig:
    """Feature selection, classifier and calibration (paper defaults).

    Attributes:
        n_features: features kept by AdaBoost selection (paper: 40; Haar banks).
        selection_bins: threshold bins per feature during selection.
        classifier: ``"auto"`` (Haar banks: ``"adaboost"``, the paper; channel banks:
            ``"trees"``), ``"adaboost"`` (boosted stumps on the selected features), ``"trees"``
            (boosted depth-``tree_depth`` trees over the whole pool, with a soft cascade) or
            ``"svm"``.
        variant: boosting variant, ``"discrete"`` (paper eq. 9), ``"real"`` or ``"gentle"``;
            ``None``: discrete for stumps, real for trees (Dollár's ACF).
        n_estimators: boosting rounds of stumps on the selected features (default:
            ``n_features``; at most 100,000, what a model file holds).
        n_trees, tree_depth: trees of the final round (mining rounds train fewer, see
            :class:`MiningConfig`; at most 100,000) and their depth.
        feature_fraction, weight_trimming: share of the pool searched per tree, and share of
            the weight left out of the split search (see :class:`torchtrack.learn.BoostedTrees`).
        cascade: the soft cascade stored in the model (used by scans; scoring boxes always
            evaluates every tree): ``"constant"`` (default; Dollár's constant soft cascade at
            ``cascade_threshold``: a window is dropped as soon as its running margin falls
            below it; ACF uses -1), ``"held-out"`` (a constant soft cascade whose threshold is
            set from the held-out positives: the highest value, at most
            ``cascade_threshold``, that rejects at most ``cascade_miss`` of the held-out
            positives whose calibrated probability reaches ``cascade_probability``; it can
            land far lower than -1, and a lower threshold costs scan time and lets through
            windows the full classifier wrongly accepts: docs/detectors.md),
            ``"backward"`` (Bourdev & Brandt's direct backward pruning on the held-out
            positives, see ``cascade_probability``) or ``"none"``.
        cascade_threshold: the constant cascade's threshold on the running margin
            (``"held-out"``: its upper bound).
        tracking_trees: trees of the model's tracking head (:attr:`Detector.tracking_head`):
            the first ``tracking_trees`` trees with a Platt calibration of their own, fitted on
            the same held-out windows; the particle-filter trackers score windows with it
            (0, or at least ``n_trees``: no head, trackers use the whole classifier).
        box_regression: channel detectors: fit a box regressor
            (:mod:`torchtrack.detect.box_regression`) on jittered copies of the positive crops'
            windows, so that scans report each detection where the crops put the object
            (needs positives with context around ``data.region``: INRIA's 96x160 crops).
        cascade_probability, cascade_miss: the held-out positives a cascade must keep:
            those whose calibrated probability reaches ``cascade_probability``, all but a
            ``cascade_miss`` share of them (``"held-out"``: the constant threshold is the
            ``cascade_miss`` quantile of their lowest running margins; ``"backward"``: the
            threshold after each tree is the ``cascade_miss`` quantile of their running margins
            after that tree; ``cascade_miss = 0``: none of them is ever rejected). Held-out
            crops are cleaner than objects in real scenes, so per-tree backward thresholds
            reject more real objects than one constant threshold (docs/benchmarks/uiuc.md).
        svm_kernel, svm_c: SVM kernel (``"rbf"`` / ``"linear"``) and C.
        calibration: ``"platt"`` (paper eq. 5-8) or ``"isotonic"``.
        calibration_fraction: share of the training crops held out for calibration (paper: 0.3).
        min_train_per_class: fewest training crops per class (after the hold-out, mirror images
            included) a run accepts without ``force``: boosting picks ``n_features`` thresholds
            from these crops, and with a handful of them it only memorises them.
        min_calibration_per_class: fewest held-out crops per class for the calibration fit:
            Platt's two parameters (and the held-out detection rate) from fewer are noise.
    """

    n_features: int = 40
    selection_bins: int = 256
    classifier: str = "auto"
    variant: str | None = None
    n_estimators: int | None = None
    n_trees: int = 1024
    tree_depth: int = 2
    feature_fraction: float = 0.5
    weight_trimming: float = 0.02
    cascade: str = "constant"
    cascade_threshold: float = -1.0
    tracking_trees: int = 64
    box_regression: bool = False
    cascade_probability: float = 0.5
    cascade_miss: float = 0.01
    svm_kernel: str = "rbf"
    svm_c: float = 1.0
    calibration: str = "platt"
    calibration_fraction: float = 0.3
    min_train_per_class: int = 20
    min_calibration_per_class: int = 10


@dataclass
class MiningConfig:
    """Hard-negative mining: after training, scan ``negative_images`` densely, add the
    ``per_round`` highest-scoring windows as negatives and retrain, ``rounds`` times.

    Channel detectors: round ``r`` of ``R`` trains ``max(32, n_trees / 4^(R - r))`` trees
    (Dollár's ACF schedule: 32, 128, 512, 2048), scans the training images with the constant
    soft cascade ``margin`` (windows whose running margin drops below it are dropped), and adds
    the windows that end at or above ``margin``, at most ``per_round`` (the highest first, no
    image more than twice its share). Mining stops early once the share of scanned windows
    that are false positives is at most ``target_fpr``; when the last round ends above it,
    training warns (:class:`~torchtrack.errors.TrainingWarning`).

    Attributes:
        rounds: number of mining rounds (0: off; at most :data:`MAX_MINING_ROUNDS`, 100).
        per_round: hard negatives added per round.
        scale_step: ratio between successive scan scales.
        stride: scan step as a fraction of the window width at each scale.
        min_scale: smallest scan scale (channel detectors; default: the data's
            ``negative_min_scale``).
        max_scale: largest scan scale (x window); default: what fits the image.
        margin: channel detectors: the margin from which a window counts as a false positive.
        target_fpr: channel detectors: stop mining when false positives per scanned window
            reach this.
    """

    rounds: int = 0
    per_round: int = 1000
    scale_step: float = 1.2
    stride: float = 0.1
    min_scale: float | None = None
    max_scale: float | None = None
    margin: float = -1.0
    target_fpr: float = 1e-4


@dataclass
class TrainConfig:
    """A detector training run: ``window = (H, W)`` plus the sections above."""

    name: str = "detector"
    window: list[int] = field(default_factory=lambda: [128, 64])
    seed: int = 0
    data: DataConfig = field(default_factory=DataConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    learn: LearnConfig = field(default_factory=LearnConfig)
    mining: MiningConfig = field(default_factory=MiningConfig)

    def validate(self) -> TrainConfig:
        """Check values; returns ``self``. Raises :class:`ConfigError` naming the key."""
        w = self.window
        if not (isinstance(w, (list, tuple)) and len(w) == 2 and all(_posint(v) for v in w)):
            raise ConfigError(f"window must be [H, W] positive integers, got {w!r}")
        from torchtrack.detect.model_checks import LIMITS, name_error

        side = LIMITS.window_side
        if not all(4 <= v <= side for v in w):
            raise ConfigError(
                f"window must be [H, W] with sides in [4, {side}] pixels (what a model file may "
                f"hold), got {list(w)!r}"
            )
        seed = self.seed
        if not (isinstance(seed, int) and not isinstance(seed, bool) and 0 <= seed < 2**63):
            raise ConfigError(f"seed must be an integer in [0, 2^63 - 1], got {self.seed!r}")
        bad_name = name_error(self.name)  # what a model file may hold: here, not after training
        if bad_name:
            raise ConfigError(bad_name)
        d = self.data
        if not d.positives:
            raise ConfigError("data.positives must name at least one folder of positive crops")
        if not 0 <= d.random_negatives <= MAX_RANDOM_NEGATIVES:
            raise ConfigError(
                f"data.random_negatives must be in [0, {MAX_RANDOM_NEGATIVES}] (windows held in "
                f"memory), got {d.random_negatives}"
            )
        from torchtrack.io.crops import check_crop_folders

        check_crop_folders(
            {
                f"data.{key}": getattr(d, key)
                for key in ("positives", "negatives", "negative_images")
            },
            "data.positives",
        )
        if not d.negatives and not (d.negative_images and d.random_negatives > 0):
            raise ConfigError(
                "no negatives: give data.negatives (crop folders) or data.negative_images with "
                "data.random_negatives > 0"
            )
        if (d.region is None) != (d.crop_size is None):
            raise ConfigError("data.region and data.crop_size go together (give both or neither)")
        if d.crop_size is not None and not (
            len(d.crop_size) == 2 and all(_posint(v) for v in d.crop_size)
        ):  # a third number was ignored, a missing one an IndexError traceback
            raise ConfigError(
                f"data.crop_size must be [H, W] positive integers, got {d.crop_size!r}"
            )
        if d.region is not None and not (
            len(d.region) == 4
            and all(isinstance(v, int) and not isinstance(v, bool) for v in d.region)
        ):
            raise ConfigError(f"data.region must be [x, y, w, h] integers, got {d.region!r}")
        if d.object is not None:
            self.object_box()
        if (
            not isinstance(d.positive_scales, list)
            or not d.positive_scales
            or not all(_isnum(q) and 0 < q <= 1 for q in d.positive_scales)
        ):
            raise ConfigError(
                f"data.positive_scales must be a non-empty list of numbers in (0, 1], got "
                f"{d.positive_scales!r}"
            )
        if (
            not isinstance(d.positive_jitter, int)
            or isinstance(d.positive_jitter, bool)
            or not 0 <= d.positive_jitter <= 64
        ):
            raise ConfigError(
                f"data.positive_jitter must be an integer in [0, 64] pixels, got {d.positive_jitter!r}"
            )
        if not (_isnum(d.blur_copies) and 0 <= d.blur_copies <= 10):
            raise ConfigError(
                f"data.blur_copies must be a number in [0, 10] pixels (0: none), got "
                f"{d.blur_copies!r}"
            )
        if not (_isnum(d.blur_share) and 0 < d.blur_share <= 1):
            raise ConfigError(f"data.blur_share must be a number in (0, 1], got {d.blur_share!r}")
        f = self.features
        if f.kind not in ("haar", "channels"):
            raise ConfigError(f"features.kind must be 'haar' or 'channels', got {f.kind!r}")
        if f.kind == "haar" and d.blur_copies:
            raise ConfigError(
                "data.blur_copies applies to channel models (features.kind = 'channels'); the "
                "Haar recipe trains on the crops as they are"
            )
        if f.sizes is not None and not f.sizes:  # was taken as "not given": n_scales sizes
            raise ConfigError(
                "features.sizes = [] names no filter size; give sizes or leave the key out (the "
                "bank then takes features.n_scales sizes)"
            )
        if f.kind == "channels":
            from torchtrack.features.channels import _check_geometry, check_channel_values

            # the channel set's own checks, with the keys as written here ("orientations must
            # ..." did not say where)
            check_channel_values(
                f.channels,
                f.orientations,
                f.norm_radius,
                f.norm_const,
                f.gradient_lambda,
                prefix="features.",
            )
            f.channel_set()
            _check_geometry(tuple(w), f.cell, "features.cell")
            from torchtrack.features.channels import _MAX_FEATURES

            for name in ("boxes", "haar"):  # random features: 2e9 ran out of memory
                v = getattr(f, name)
                if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= _MAX_FEATURES:
                    raise ConfigError(
                        f"features.{name} must be an integer in [0, {_MAX_FEATURES}] (the most "
                        f"features a channel bank holds), got {v!r}"
                    )
            if not isinstance(f.cells, bool):
                raise ConfigError(f"features.cells must be true or false, got {f.cells!r}")
            if not (f.cells or f.boxes or f.haar):  # the bank's check ran in the training
                raise ConfigError(
                    "features.cells = false with features.boxes = 0 and features.haar = 0 leaves "
                    "the channel bank empty"
                )
            for q in d.positive_scales:
                if abs(f.cell * q - round(f.cell * q)) > 1e-9:
                    raise ConfigError(
                        f"data.positive_scales: features.cell {f.cell} x {q} is not a whole "
                        "number of pixels"
                    )
        if not (d.negative_min_scale > 0 and math.isfinite(d.negative_min_scale)):
            raise ConfigError("data.negative_min_scale must be a positive number")
        top = d.negative_max_scale
        if top is not None and not (math.isfinite(top) and top >= d.negative_min_scale):
            raise ConfigError(
                f"data.negative_max_scale must be a finite number >= data.negative_min_scale "
                f"({d.negative_min_scale:g}), got {top!r}"
            )
        top = self.mining.max_scale
        if top is not None and not (math.isfinite(top) and top > 0):
            raise ConfigError(f"mining.max_scale must be a finite number > 0, got {top!r}")
        lr = self.learn
        if lr.classifier not in ("auto", "adaboost", "trees", "svm"):
            raise ConfigError(
                f"learn.classifier must be 'auto', 'adaboost', 'trees' or 'svm', got "
                f"{lr.classifier!r}"
            )
        if lr.classifier == "trees" and f.kind != "channels":
            raise ConfigError("learn.classifier = 'trees' needs features.kind = 'channels'")
        if f.kind == "channels" and lr.classifier not in ("auto", "trees"):
            raise ConfigError(
                f"features.kind = 'channels' trains boosted trees: learn.classifier must be "
                f"'auto' or 'trees', got {lr.classifier!r}"
            )
        if lr.variant not in (None, "discrete", "real", "gentle"):
            raise ConfigError(
                f"learn.variant must be 'discrete', 'real' or 'gentle', got {lr.variant!r}"
            )
        if lr.variant is not None and lr.classifier == "svm":  # it was taken and ignored
            raise ConfigError(
                f"learn.variant = {lr.variant!r} is the boosting variant: learn.classifier = "
                "'svm' trains no boosted classifier (leave the variant out, or train adaboost)"
            )
        for name in ("n_trees", "tree_depth"):
            if not _posint(getattr(lr, name)):
                raise ConfigError(
                    f"learn.{name} must be a positive integer, got {getattr(lr, name)!r}"
                )
        # what a model file may hold: refused here, not after the training
        for name in ("n_trees", "n_estimators"):
            v = getattr(lr, name)
            if v is not None and not (_posint(v) and v <= LIMITS.stumps):
                raise ConfigError(
                    f"learn.{name} must be an integer in [1, {LIMITS.stumps}] (what a model file "
                    f"holds), got {v!r}"
                )
        if lr.tree_depth > 4:
            raise ConfigError(f"learn.tree_depth must be at most 4, got {lr.tree_depth}")
        if not (_isnum(lr.feature_fraction) and 0 < lr.feature_fraction <= 1):
            raise ConfigError(
                f"learn.feature_fraction must be in (0, 1], got {lr.feature_fraction!r}"
            )
        if not (_isnum(lr.weight_trimming) and 0 <= lr.weight_trimming < 1):
            raise ConfigError(
                f"learn.weight_trimming must be in [0, 1), got {lr.weight_trimming!r}"
            )
        if lr.cascade not in ("held-out", "constant", "backward", "none"):
            raise ConfigError(
                "learn.cascade must be 'held-out', 'constant', 'backward' or 'none', "
                f"got {lr.cascade!r}"
            )
        if isinstance(lr.tracking_trees, bool) or not (
            isinstance(lr.tracking_trees, int) and lr.tracking_trees >= 0
        ):
            raise ConfigError(
                f"learn.tracking_trees must be a non-negative integer, got {lr.tracking_trees!r}"
            )
        if not isinstance(lr.box_regression, bool):
            raise ConfigError(
                f"learn.box_regression must be true or false, got {lr.box_regression!r}"
            )
        if not (_isnum(lr.cascade_threshold) and abs(lr.cascade_threshold) <= 1e6):
            raise ConfigError(
                f"learn.cascade_threshold must be a running margin within +-1e6, got "
                f"{lr.cascade_threshold!r}"
            )
        if not (_isnum(lr.cascade_miss) and 0 <= lr.cascade_miss < 0.5):
            raise ConfigError(f"learn.cascade_miss must be in [0, 0.5), got {lr.cascade_miss!r}")
        if not (_isnum(lr.cascade_probability) and 0 <= lr.cascade_probability < 1):
            raise ConfigError(
                f"learn.cascade_probability must be in [0, 1), got {lr.cascade_probability!r}"
            )
        if not (_isnum(lr.svm_c) and lr.svm_c > 0):
            raise ConfigError(f"learn.svm_c must be a finite number > 0, got {lr.svm_c!r}")
        if lr.svm_kernel not in ("rbf", "linear"):
            raise ConfigError(f"learn.svm_kernel must be 'rbf' or 'linear', got {lr.svm_kernel!r}")
        if lr.calibration not in ("platt", "isotonic"):
            raise ConfigError(
                f"learn.calibration must be 'platt' or 'isotonic', got {lr.calibration!r}"
            )
        if not 0.0 < lr.calibration_fraction < 1.0:
            raise ConfigError(
                f"learn.calibration_fraction must be in (0, 1), got {lr.calibration_fraction}"
            )
        if not _posint(lr.n_features):
            raise ConfigError(f"learn.n_features must be a positive integer, got {lr.n_features!r}")
        if not (_posint(lr.selection_bins) and 2 <= lr.selection_bins <= 256):
            # the selection's own check ran only after every crop's features were computed
            raise ConfigError(
                f"learn.selection_bins must be an integer in [2, 256], got {lr.selection_bins!r}"
            )
        for k in ("min_train_per_class", "min_calibration_per_class"):
            v = getattr(lr, k)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ConfigError(f"learn.{k} must be an integer >= 1, got {v!r}")
        m = self.mining
        if not 0 <= m.rounds <= MAX_MINING_ROUNDS:
            raise ConfigError(
                f"mining.rounds must be in [0, {MAX_MINING_ROUNDS}] (each scans every negative "
                f"image and retrains), got {m.rounds}"
            )
        if m.per_round < 1:
            raise ConfigError(f"mining.per_round must be >= 1, got {m.per_round}")
        from torchtrack.detect.scan import MIN_SCALE_STEP

        if not MIN_SCALE_STEP <= m.scale_step < math.inf:
            raise ConfigError(
                f"mining.scale_step must be a finite number >= {MIN_SCALE_STEP:g}, got "
                f"{m.scale_step}"
            )
        if not 0.0 < m.stride <= 1.0:
            raise ConfigError(f"mining.stride must be in (0, 1], got {m.stride}")
        if m.rounds > 0 and not d.negative_images:
            raise ConfigError("mining.rounds > 0 needs data.negative_images to scan")
        if m.min_scale is not None and not (_isnum(m.min_scale) and m.min_scale > 0):
            raise ConfigError(f"mining.min_scale must be a positive number, got {m.min_scale!r}")
        if not _isnum(m.margin):
            raise ConfigError(f"mining.margin must be a number, got {m.margin!r}")
        if not (_isnum(m.target_fpr) and 0 <= m.target_fpr < 1):
            raise ConfigError(f"mining.target_fpr must be in [0, 1), got {m.target_fpr!r}")
        # a huge n_scales built a list of that many sizes; whether they fit the window is the
        # bank's check (haar_bank), once the data is known to be there
        if f.kind == "haar" and not (_posint(f.n_scales) and f.n_scales <= LIMITS.bank_sizes):
            raise ConfigError(
                f"features.n_scales must be an integer in [1, {LIMITS.bank_sizes}] (the most "
                f"filter sizes a bank holds), got {f.n_scales!r}"
            )
        if f.kind == "haar":
            self._check_haar_keys()
        return self

    def _check_haar_keys(self) -> None:
        """``features.sizes / n_scales / stride / min_std`` of a Haar bank, before any crop is
        read: the checks a model file makes of its bank
        (:func:`~torchtrack.detect.model_checks._check_haar_bank`: bounds and feature count),
        named as the keys are written here (such a bank trained to the end, then its model was
        refused when written; the bank's own messages said ``stride`` or ``min_std``)."""
        from torchtrack.detect.model_checks import _check_haar_bank
        from torchtrack.errors import ModelFormatError
        from torchtrack.features.haar import default_sizes

        f = self.features
        window = (int(self.window[0]), int(self.window[1]))
        sizes = f.sizes
        if sizes is None:
            sizes = list(default_sizes(window, f.n_scales, key="features.n_scales"))
        desc = {"window": list(window), "sizes": sizes, "stride": f.stride, "min_std": f.min_std}
        try:
            _check_haar_bank(desc, window, _HAAR_KEYS)
        except ModelFormatError as exc:
            raise ConfigError(f"{exc} (a Haar bank no model file may hold)") from None

    def classifier(self) -> str:
        """``learn.classifier`` with ``"auto"`` resolved (Haar: adaboost, channels: trees)."""
        c = self.learn.classifier
        if c == "auto":
            return "trees" if self.features.kind == "channels" else "adaboost"
        return c

    def variant(self) -> str:
        """``learn.variant`` with ``None`` resolved (stumps: discrete, trees: real)."""
        if self.learn.variant is not None:
            return self.learn.variant
        return "real" if self.classifier() == "trees" else "discrete"

    def object_box(self) -> tuple[float, float, float, float] | None:
        """``data.object`` as fractions of the detector window (see
        :attr:`torchtrack.detect.Detector.object_box`); ``None`` when not given.

        Raises:
            ConfigError: not four numbers, or not inside the window.
        """
        from torchtrack.detect.detector import check_object_box
        from torchtrack.errors import ModelFormatError

        d = self.data
        if d.object is None:
            return None
        if not isinstance(d.object, (list, tuple)) or len(d.object) != 4:
            raise ConfigError(f"data.object must be [x, y, w, h] pixels, got {d.object!r}")
        if d.region is not None:
            rx, ry, rw, rh = (float(v) for v in d.region)
        else:
            rx, ry, rh, rw = 0.0, 0.0, float(self.window[0]), float(self.window[1])
        try:
            x, y, w, h = (float(v) for v in d.object)
            return check_object_box([(x - rx) / rw, (y - ry) / rh, w / rw, h / rh])
        except (TypeError, ValueError, ModelFormatError) as exc:
            raise ConfigError(
                f"data.object {d.object!r} must be four numbers inside the window region ({exc})"
            ) from None

    def to_dict(self) -> dict[str, Any]:
        return _asdict(self)


def _posint(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v > 0


def _isnum(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _asdict(obj: Any) -> Any:
    if is_dataclass(obj):
        return {f.name: _asdict(getattr(obj, f.name)) for f in fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [_asdict(v) for v in obj]
    return obj


def _fill(cls: type, values: dict[str, Any], where: str) -> Any:
    if not isinstance(values, dict):
        raise ConfigError(f"[{where}] must be a table, got {type(values).__name__}")
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in [{where}]; known keys: {sorted(known)}")
    import typing

    from torchtrack.track.config import coerce_value  # the tracker configs' typed check

    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, v in values.items():
        sub = {
            "data": DataConfig,
            "features": FeatureConfig,
            "learn": LearnConfig,
            "mining": MiningConfig,
        }
        if cls is TrainConfig and name in sub:
            kwargs[name] = _fill(sub[name], v, name)
        else:  # each value of the type its key says (a string where a count goes: named)
            kwargs[name] = coerce_value(v, hints[name], name, f"[{where}]", 2**63 - 1)
    return cls(**kwargs)


def _resolve(p: str, base: Path) -> str:
    s = os.path.expanduser(os.path.expandvars(str(p)))
    if "$" in s:
        raise ConfigError(f"path {p!r} uses an environment variable that is not set")
    q = Path(s)
    return str(q if q.is_absolute() else (base / q))


#: a Haar bank's fields as a training config names them (model_checks._check_haar_bank)
_HAAR_KEYS = {
    "sizes": "features.sizes",
    "size": "features.sizes: filter size",
    "stride": "features.stride",
    "min_std": "features.min_std",
}

#: the ``[mining]`` keys only channel-feature detectors read (:class:`MiningConfig`)
_CHANNEL_MINING_KEYS = ("min_scale", "margin", "target_fpr")


def load_train_config(
    path: str | os.PathLike, overrides: dict[str, Any] | None = None
) -> TrainConfig:
    """Read a TOML training config; relative paths resolve against the file's folder.

    Args:
        path: the TOML file.
        overrides: ``{"learn.n_features": 80, ...}`` applied after reading (CLI options).

    Raises:
        ConfigError: unreadable TOML, an unknown key (named), or an invalid value.

    Warns:
        UserWarning: ``mining.target_fpr``, ``margin`` or ``min_scale`` set (in the file or
            ``overrides``) for a Haar detector, which does not use them.
    """
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file {str(p)!r} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {str(p)!r} is not valid TOML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"config file {str(p)!r} is not valid TOML: not UTF-8 text ({exc.reason} at byte "
            f"{exc.start})"
        ) from None
    cfg = _fill(TrainConfig, raw, "top level")
    base = p.resolve().parent
    d = cfg.data
    d.positives = [_resolve(x, base) for x in d.positives]
    d.negatives = [_resolve(x, base) for x in d.negatives]
    d.negative_images = [_resolve(x, base) for x in d.negative_images]
    d.exclude = [_resolve(x, base) for x in d.exclude]
    for key, value in (overrides or {}).items():
        apply_override(cfg, key, value)
    cfg.validate()
    mining = raw.get("mining", {})
    given = [k for k in _CHANNEL_MINING_KEYS if k in mining or f"mining.{k}" in (overrides or {})]
    if cfg.features.kind == "haar" and given:
        # a warning, not an error: the shipped channel configs set these and say the paper's
        # Haar setting is one key away (features.kind = "haar"); only the keys the file or an
        # override sets are named, the defaults are carried by every config
        import warnings

        keys = ", ".join(f"mining.{k} = {getattr(cfg.mining, k)!r}" for k in given)
        many = len(given) > 1
        warnings.warn(
            f"{str(p)!r}: {keys} appl{'y' if many else 'ies'} to channel-feature detectors only "
            "(features.kind = 'channels'); this Haar detector (features.kind = 'haar') mines its "
            f"mining.rounds without {'them' if many else 'it'}",
            stacklevel=2,
        )
    return cfg


def apply_override(cfg: TrainConfig, key: str, value: Any) -> None:
    """Set ``cfg.<section>.<name>`` (``key = "learn.n_features"``) or a top-level key."""
    parts = key.split(".")
    obj: Any = cfg
    for part in parts[:-1]:
        if not hasattr(obj, part):
            raise ConfigError(f"unknown config section {part!r} in {key!r}")
        obj = getattr(obj, part)
    if not is_dataclass(obj) or parts[-1] not in {f.name for f in fields(obj)}:
        raise ConfigError(f"unknown config key {key!r}")
    setattr(obj, parts[-1], value)


def excluded_names(data: DataConfig) -> set[str]:
    """The file names of every list in ``data.exclude`` (the held-out test splits)."""
    out: set[str] = set()
    for f in data.exclude:
        out |= read_name_list(f)
    return out


def read_name_list(path: str | os.PathLike) -> set[str]:
    """File names listed one per line (blank lines and ``#`` comments ignored).

    Raises:
        ConfigError: the file does not exist or is not UTF-8 text.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"name list {str(p)!r} does not exist") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"name list {str(p)!r} is not a text file of names: not UTF-8 ({exc.reason} at "
            f"byte {exc.start})"
        ) from None
    return {ln.split("#", 1)[0].strip() for ln in text.splitlines()} - {""}
