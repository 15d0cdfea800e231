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
        mirror_positives, mirror_negatives: add left-right mirror images.
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
    mirror_positives: bool = True
    mirror_negatives: bool = False
    random_negatives: int = 0
    negative_min_scale: float = 1.0
    negative_max_scale: float | None = None
    exclude: list[str] = field(default_factory=list)
    strict: bool = False


@dataclass
class FeatureConfig:
    """Haar bank (see :func:`torchtrack.features.haar_bank`)."""

    n_scales: int = 3
    sizes: list[int] | None = None
    stride: int = 1
    min_std: float = 1.0


@dataclass
class LearnConfig:
    """Feature selection, classifier and calibration (paper defaults).

    Attributes:
        n_features: features kept by AdaBoost selection (paper: 40).
        selection_bins: threshold bins per feature during selection.
        classifier: ``"adaboost"`` (boosted stumps on the selected features) or ``"svm"``.
        variant: boosting variant, ``"discrete"`` (paper eq. 9), ``"real"`` or ``"gentle"``.
        n_estimators: boosting rounds on the selected features (default: ``n_features``).
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
    classifier: str = "adaboost"
    variant: str = "discrete"
    n_estimators: int | None = None
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

    Attributes:
        rounds: number of mining rounds (0: off).
        per_round: hard negatives added per round.
        scale_step: ratio between successive scan scales.
        stride: scan step as a fraction of the window width at each scale.
        max_scale: largest scan scale (x window); default: what fits the image.
    """

    rounds: int = 0
    per_round: int = 1000
    scale_step: float = 1.2
    stride: float = 0.1
    max_scale: float | None = None


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
        d = self.data
        if not d.positives:
            raise ConfigError("data.positives must name at least one folder of positive crops")
        if not d.negatives and not (d.negative_images and d.random_negatives > 0):
            raise ConfigError(
                "no negatives: give data.negatives (crop folders) or data.negative_images with "
                "data.random_negatives > 0"
            )
        if d.random_negatives < 0:
            raise ConfigError(f"data.random_negatives must be >= 0, got {d.random_negatives}")
        if (d.region is None) != (d.crop_size is None):
            raise ConfigError("data.region and data.crop_size go together (give both or neither)")
        if d.object is not None:
            self.object_box()
        if not (d.negative_min_scale > 0 and math.isfinite(d.negative_min_scale)):
            raise ConfigError("data.negative_min_scale must be a positive number")
        lr = self.learn
        if lr.classifier not in ("adaboost", "svm"):
            raise ConfigError(
                f"learn.classifier must be 'adaboost' or 'svm', got {lr.classifier!r}"
            )
        if lr.variant not in ("discrete", "real", "gentle"):
            raise ConfigError(
                f"learn.variant must be 'discrete', 'real' or 'gentle', got {lr.variant!r}"
            )
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
        for k in ("min_train_per_class", "min_calibration_per_class"):
            v = getattr(lr, k)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ConfigError(f"learn.{k} must be an integer >= 1, got {v!r}")
        if lr.n_estimators is not None and not _posint(lr.n_estimators):
            raise ConfigError(
                f"learn.n_estimators must be a positive integer, got {lr.n_estimators!r}"
            )
        m = self.mining
        if m.rounds < 0 or m.per_round < 1:
            raise ConfigError("mining.rounds must be >= 0 and mining.per_round >= 1")
        if not m.scale_step > 1.0:
            raise ConfigError(f"mining.scale_step must be > 1, got {m.scale_step}")
        if not 0.0 < m.stride <= 1.0:
            raise ConfigError(f"mining.stride must be in (0, 1], got {m.stride}")
        if m.rounds > 0 and not d.negative_images:
            raise ConfigError("mining.rounds > 0 needs data.negative_images to scan")
        return self

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
        else:
            kwargs[name] = v
    return cls(**kwargs)


def _resolve(p: str, base: Path) -> str:
    s = os.path.expanduser(os.path.expandvars(str(p)))
    if "$" in s:
        raise ConfigError(f"path {p!r} uses an environment variable that is not set")
    q = Path(s)
    return str(q if q.is_absolute() else (base / q))


def load_train_config(
    path: str | os.PathLike, overrides: dict[str, Any] | None = None
) -> TrainConfig:
    """Read a TOML training config; relative paths resolve against the file's folder.

    Args:
        path: the TOML file.
        overrides: ``{"learn.n_features": 80, ...}`` applied after reading (CLI options).

    Raises:
        ConfigError: unreadable TOML, an unknown key (named), or an invalid value.
    """
    p = Path(path)
    try:
        raw = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"config file {str(p)!r} does not exist") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {str(p)!r} is not valid TOML: {exc}") from None
    cfg = _fill(TrainConfig, raw, "top level")
    base = p.resolve().parent
    d = cfg.data
    d.positives = [_resolve(x, base) for x in d.positives]
    d.negatives = [_resolve(x, base) for x in d.negatives]
    d.negative_images = [_resolve(x, base) for x in d.negative_images]
    d.exclude = [_resolve(x, base) for x in d.exclude]
    for key, value in (overrides or {}).items():
        apply_override(cfg, key, value)
    return cfg.validate()


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


def read_name_list(path: str | os.PathLike) -> set[str]:
    """File names listed one per line (blank lines and ``#`` comments ignored).

    Raises:
        ConfigError: the file does not exist.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"name list {str(p)!r} does not exist") from None
    return {ln.split("#", 1)[0].strip() for ln in text.splitlines()} - {""}
