"""Typed tracker configurations: every default in one dataclass, loaded from TOML.

``configs/trackers/<name>.toml`` files hold flat ``key = value`` pairs for one tracker; unknown
keys are rejected by name, values are checked against the field's type. The same checks apply
to keyword overrides (``torchtrack track --tracker detector:n_particles=500`` or
``create_tracker("detector", n_particles=500)``).

Example::

    cfg = load_tracker_config("configs/trackers/detector.toml", DetectorTrackerConfig)
    cfg = apply_overrides(cfg, {"n_particles": 500})
"""

from __future__ import annotations

import dataclasses
import math
import os
import tomllib
import types
import typing
from dataclasses import dataclass, field
from typing import Any, TypeVar

from torchtrack.errors import ConfigError

__all__ = [
    "DetectorTrackerConfig",
    "HistogramTrackerConfig",
    "apply_overrides",
    "config_from_dict",
    "load_tracker_config",
    "resolve_tracker_config",
]

C = TypeVar("C")


@dataclass
class DetectorTrackerConfig:
    """Calibrated-detector particle filter (Chateau et al. 2006).

    Attributes:
        model: detector: a bundled model name (``pedestrian``, ``vehicle``) or a model file
            written by ``torchtrack train``.
        n_particles: particles per target (paper: 200).
        dynamics: TOML file of the AR dynamics ``A, B, Sigma`` (eq. 4) as written by
            ``tools/fit_dynamics.py``; empty: the fitted ``dynamics_chateau.toml`` shipped
            with torchtrack.
        visible_threshold: the target is reported visible while the mean calibrated
            probability of the particles (the evidence) is at least this.
        context: height of the detector window over the height of the tracked object box
            (e.g. about 1.33 for INRIA-style pedestrian windows that keep a margin around the
            person). ``0``: chosen on the first frame, among ``context_candidates``, as the
            window at the given box's centre with the highest detector probability.
        context_candidates: window-over-box height ratios tried when ``context = 0``.
        scan_context: for auto-initialisation (no box): the object box reported is the
            detection window divided by this.
        likelihood_floor: smallest likelihood (keeps weights finite when every window is ~0).
        likelihood_power: particle weights are ``max(p, floor) ** likelihood_power``; 1 is the
            paper's eq. (11) (the calibrated probability itself); > 1 sharpens it.
        estimator: ``mean`` (paper Fig. 1 d), ``best`` or ``mode``.
        resample: resampling scheme (``torchtrack.filter.RESAMPLERS``).
        scan_threshold: auto-initialisation: smallest probability of a detection.
        scan_min_scale, scan_scale_step, scan_stride: the first-frame scan (section 4.2), see
            :func:`torchtrack.detect.scan.sliding_windows`.
        init_top_n: auto-initialisation: particles are importance-sampled from the ``N``
            highest-scoring scan windows overlapping the detection.
        n_targets: auto-initialisation: how many detections to track (best first).
    """

    model: str = "pedestrian"
    n_particles: int = 200
    dynamics: str = ""
    visible_threshold: float = 0.1
    context: float = 0.0
    context_candidates: list[float] = field(
        default_factory=lambda: [1.0, 1.1, 1.2, 1.3, 1.4, 1.5, 1.6]
    )
    scan_context: float = 1.0
    likelihood_floor: float = 1e-6
    likelihood_power: float = 1.0
    estimator: str = "mean"
    resample: str = "systematic"
    scan_threshold: float = 0.5
    scan_min_scale: float = 0.5
    scan_scale_step: float = 1.15
    scan_stride: float = 0.08
    init_top_n: int = 50
    n_targets: int = 1

    def validate(self) -> None:
        _positive_int(self, "n_particles", "init_top_n", "n_targets")
        _in_unit(self, "visible_threshold", "scan_threshold")
        if not 0.0 <= self.likelihood_floor < 1.0:
            raise ConfigError(f"likelihood_floor must be in [0, 1), got {self.likelihood_floor}")
        if not (math.isfinite(self.likelihood_power) and self.likelihood_power > 0):
            raise ConfigError(f"likelihood_power must be > 0, got {self.likelihood_power}")
        if self.context != 0 and not self.context > 0:
            raise ConfigError(f"context must be > 0 (or 0 to choose it), got {self.context}")
        if not self.context_candidates or any(not c > 0 for c in self.context_candidates):
            raise ConfigError(
                f"context_candidates must be positive numbers, got {self.context_candidates}"
            )
        if not self.scan_context > 0:
            raise ConfigError(f"scan_context must be > 0, got {self.scan_context}")
        if not self.scan_min_scale > 0:
            raise ConfigError(f"scan_min_scale must be > 0, got {self.scan_min_scale}")
        _estimator_and_scheme(self)


@dataclass
class HistogramTrackerConfig:
    """Colour-histogram particle filter (Pérez et al. 2002) on Klein et al.'s filter.

    Attributes:
        n_particles: particles (Klein et al.: J = 2000 for every observation model).
        sigma_xy, sigma_wh: motion noise of Klein et al. eq. (1) (6.4 and 0.64).
        lam: ``lambda`` of the likelihood ``exp(-lambda D^2)`` (Pérez et al.: 20).
        n_h, n_s, n_v, s_min, v_min: HSV binning (Pérez et al.: 10, 10, 10, 0.1, 0.2).
        grid: histogram samples per box side (``grid^2`` samples per particle).
        update_rate: reference update ``q = (1 - a) q + a p(estimate)`` per visible frame
            (0: the first frame's histogram is kept, as in Klein et al.'s baseline).
        visible_threshold: visible while the best particle's Bhattacharyya coefficient is at
            least this.
        estimator: ``mean`` (Klein et al. eq. 2), ``best`` or ``mode``.
        resample: resampling scheme.
    """

    n_particles: int = 2000
    sigma_xy: float = 6.4
    sigma_wh: float = 0.64
    lam: float = 20.0
    n_h: int = 10
    n_s: int = 10
    n_v: int = 10
    s_min: float = 0.1
    v_min: float = 0.2
    grid: int = 16
    update_rate: float = 0.0
    visible_threshold: float = 0.5
    estimator: str = "mean"
    resample: str = "systematic"

    def validate(self) -> None:
        _positive_int(self, "n_particles", "n_h", "n_s", "n_v", "grid")
        _in_unit(self, "update_rate", "visible_threshold")
        if not self.lam > 0:
            raise ConfigError(f"lam must be > 0, got {self.lam}")
        for k in ("sigma_xy", "sigma_wh"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"{k} must be >= 0, got {getattr(self, k)}")
        _estimator_and_scheme(self)


def _positive_int(cfg: Any, *names: str) -> None:
    for n in names:
        if getattr(cfg, n) < 1:
            raise ConfigError(f"{n} must be >= 1, got {getattr(cfg, n)}")


def _in_unit(cfg: Any, *names: str) -> None:
    for n in names:
        if not 0.0 <= getattr(cfg, n) <= 1.0:
            raise ConfigError(f"{n} must be in [0, 1], got {getattr(cfg, n)}")


def _estimator_and_scheme(cfg: Any) -> None:
    from torchtrack.filter.resample import RESAMPLERS
    from torchtrack.filter.sir import ESTIMATORS

    if cfg.estimator not in ESTIMATORS:
        raise ConfigError(
            f"unknown estimator {cfg.estimator!r}; valid: {', '.join(sorted(ESTIMATORS))}"
        )
    if cfg.resample not in RESAMPLERS:
        raise ConfigError(
            f"unknown resampling scheme {cfg.resample!r}; valid: {', '.join(sorted(RESAMPLERS))}"
        )


def _coerce(value: Any, tp: Any, key: str, where: str) -> Any:
    """Check ``value`` against the annotation ``tp`` (int, float, str, bool, list[float])."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        errors = []
        for arg in typing.get_args(tp):
            if arg is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, arg, key, where)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(errors[0] if errors else f"{where}: bad value for {key!r}")
    if origin is list:
        (item,) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: {key!r} must be a list, got {value!r}")
        return [_coerce(v, item, key, where) for v in value]
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: {key!r} must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: {key!r} must be an integer, got {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: {key!r} must be a number, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, (str, os.PathLike)):
            raise ConfigError(f"{where}: {key!r} must be a string, got {value!r}")
        return os.fspath(value)
    return value  # pragma: no cover - no other annotation is used


def config_from_dict(cls: type[C], data: dict[str, Any], where: str = "config") -> C:
    """Build ``cls`` from ``data``; unknown keys and wrong types raise :class:`ConfigError`."""
    return apply_overrides(cls(), data, where)


def apply_overrides(cfg: C, overrides: dict[str, Any], where: str = "parameters") -> C:
    """A copy of ``cfg`` with ``overrides`` applied (checked like :func:`config_from_dict`)."""
    cls = type(cfg)
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(overrides) - set(names))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; valid keys: "
            f"{', '.join(names)}"
        )
    values = {k: _coerce(v, hints[k], k, where) for k, v in overrides.items()}
    out = dataclasses.replace(cfg, **values)
    try:
        out.validate()
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    return out


def load_tracker_config(path: str | os.PathLike, cls: type[C]) -> C:
    """Load a flat TOML file into ``cls`` (relative ``dynamics`` / ``model`` paths are taken
    relative to the file when such a file exists there).

    Raises:
        ConfigError: unreadable TOML, unknown keys (named), wrong types or values.
    """
    p = os.fspath(path)
    try:
        with open(p, "rb") as f:
            data = tomllib.load(f)
    except OSError as e:
        raise ConfigError(f"cannot read tracker config {p!r}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"tracker config {p!r} is not valid TOML: {e}") from None
    base = os.path.dirname(os.path.abspath(p))
    for key in ("dynamics", "model"):
        v = data.get(key)
        if isinstance(v, str) and v and not os.path.isabs(v):
            cand = os.path.join(base, os.path.expanduser(v))
            if os.path.exists(cand):
                data[key] = cand
    return config_from_dict(cls, data, where=p)


def resolve_tracker_config(
    cls: type[C],
    config: C | str | os.PathLike | None,
    overrides: dict[str, Any] | None = None,
    where: str = "parameters",
) -> C:
    """The config a tracker runs with: ``cls()`` defaults, a given ``cls`` instance, or a TOML
    file loaded with :func:`load_tracker_config`; then keyword ``overrides`` applied and checked.
    """
    if config is None:
        cfg = cls()
    elif isinstance(config, cls):
        cfg = config
    else:
        cfg = load_tracker_config(config, cls)
    if overrides:
        return apply_overrides(cfg, overrides, where=where)
    cfg.validate()
    return cfg
