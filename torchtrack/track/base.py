"""The one tracker interface and the tracker registry.

Every tracker (ours and the OpenCV peers) is a :class:`Tracker`::

    tracker = create_tracker("mil")
    state = tracker.init(frame, box)        # frame (C, H, W) uint8 RGB, box (4,) x, y, w, h
    for frame in frames:
        state = tracker.update(frame)       # TrackState: box (B, 4), confidence (B,), visible (B,)

Boxes follow the package convention (:mod:`torchtrack.boxes`): ``x, y, w, h`` in pixels,
top-left corner, 0-based. A tracker follows ``B`` targets at once where its model allows
(``max_targets``); a single target is ``B = 1`` and :class:`TrackState` always carries the batch
axis.

``visible`` is the tracker's own belief that it sees the target. A tracker that loses the
target (an OpenCV peer returning ``ok=False``, a particle filter whose likelihood collapses)
reports ``visible=False`` and still returns a box (its last estimate); the evaluator decides
what that box counts for (see :mod:`torchtrack.eval.metrics`).

**One rule for every tracker:** a box with less than half of its area inside the frame
(:attr:`Tracker.min_visible_inside`), or one that is not finite, is never reported visible,
whatever the tracker believes: there is no image evidence outside the frame. :meth:`Tracker.init`
and :meth:`Tracker.update` apply it to what ``_init`` / ``_update`` return.

Registry: trackers register a factory under a name with :func:`register_tracker`;
:func:`create_tracker` builds one by name and raises :class:`~torchtrack.errors.ConfigError`
listing the known names for a wrong one. Modules listed in :data:`BUILTIN_TRACKER_MODULES` are
imported on first use, so registering is a matter of adding the module name there.
"""

from __future__ import annotations

import abc
import dataclasses
import importlib
import inspect
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from torchtrack.boxes import check_boxes, inside_fraction
from torchtrack.errors import ConfigError, ShapeError, TrackerError

__all__ = [
    "BUILTIN_TRACKER_MODULES",
    "TrackState",
    "Tracker",
    "TrackerInfo",
    "available_trackers",
    "create_tracker",
    "parse_tracker_spec",
    "register_tracker",
    "tracker_info",
    "tracker_names",
]

#: Modules whose import registers trackers. Later tracker modules append themselves here.
BUILTIN_TRACKER_MODULES: list[str] = [
    "torchtrack.track.opencv",
    "torchtrack.track.detector_pf",
    "torchtrack.track.histogram",
    "torchtrack.track.cotrain",
    "torchtrack.track.adaptive_haar",
    "torchtrack.track.template",
    "torchtrack.track.fused",
]


@dataclass
class TrackState:
    """What a tracker reports for one frame.

    Attributes:
        box: ``(B, 4)`` float ``x, y, w, h`` in pixels (0-based, top-left corner).
        confidence: ``(B,)`` float, the tracker's score for its estimate (tracker-specific scale;
            1 when the tracker has none).
        visible: ``(B,)`` bool, the tracker believes the target is in view and tracked.
        particles: optional ``(B, N, D)`` particle states (particle-filter trackers).
        log_weights: optional ``(B, N)`` normalised log-weights of ``particles``.
    """

    box: torch.Tensor
    confidence: torch.Tensor
    visible: torch.Tensor
    particles: torch.Tensor | None = None
    log_weights: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.box.ndim != 2 or self.box.shape[-1] != 4:
            raise ShapeError(f"TrackState.box must be (B, 4), got {tuple(self.box.shape)}")
        b = self.box.shape[0]
        if tuple(self.confidence.shape) != (b,) or tuple(self.visible.shape) != (b,):
            raise ShapeError(
                f"TrackState.confidence and .visible must be ({b},), got "
                f"{tuple(self.confidence.shape)} and {tuple(self.visible.shape)}"
            )

    @classmethod
    def single(
        cls,
        box: torch.Tensor | list[float] | tuple[float, ...],
        confidence: float = 1.0,
        visible: bool = True,
        **kwargs: Any,
    ) -> TrackState:
        """State of one target (``B = 1``) from a ``(4,)`` box and scalars."""
        b = torch.as_tensor(box, dtype=torch.float64).reshape(1, 4)
        return cls(
            box=b,
            confidence=torch.tensor([float(confidence)], dtype=torch.float64, device=b.device),
            visible=torch.tensor([bool(visible)], device=b.device),
            **kwargs,
        )


def check_tracker_generator(generator: object) -> torch.Generator | None:
    """``generator`` once it is a ``torch.Generator`` or None, what every tracker takes (5 was
    'int' object is not iterable on the first frame; a list of generators worked in some
    trackers and drew the wrong rows in others).

    Raises:
        ConfigError: anything else.
    """
    if generator is None or isinstance(generator, torch.Generator):
        return generator
    raise ConfigError(
        f"generator must be a torch.Generator or None, got {type(generator).__name__} "
        f"{generator!r}"[:200]
    )


class Tracker(abc.ABC):
    """Base class of every tracker: validate inputs, then delegate to ``_init`` / ``_update``.

    Subclasses implement :meth:`_init` and :meth:`_update`; the public :meth:`init` and
    :meth:`update` check the frame and boxes and the call order. Class attributes:

    * ``name``: the registry name.
    * ``max_targets``: how many targets one instance can follow (``None`` = any).
    * ``auto_init``: ``init(frame, box=None)`` finds the target itself (e.g. a detector scan).
    * ``min_visible_inside``: a target whose box has less than this fraction of its area inside
      the frame is reported not visible (the module's one rule; 0.5).
    * ``min_box_size``: the smallest init box side in pixels (3): a box of 1-2 pixels holds no
      appearance to learn (a histogram of a few pixels, sub-pixel Haar cells) and is refused
      with a :class:`BoxError` rather than tracked as noise.
    """

    name: ClassVar[str] = "tracker"
    max_targets: ClassVar[int | None] = 1
    auto_init: ClassVar[bool] = False
    min_visible_inside: ClassVar[float] = 0.5
    min_box_size: ClassVar[float] = 3.0

    def __init__(self) -> None:
        self._initialised = False
        self.frame_size: tuple[int, int] | None = None
        self._channels: int | None = None

    # -- public API ----------------------------------------------------------------------------
    def init(self, frame: torch.Tensor, box: torch.Tensor | None = None) -> TrackState:
        """Start tracking on ``frame``.

        Args:
            frame: ``(C, H, W)`` uint8 RGB (``C = 3``) or gray (``C = 1``).
            box: ``(4,)`` or ``(B, 4)`` x, y, w, h in pixels of the target(s) on ``frame``;
                ``None`` asks an auto-initialising tracker to find the target.

        Returns:
            The state on ``frame`` (the given boxes, visible, confidence 1 unless the tracker
            scores them).

        Raises:
            ShapeError: ``frame`` is not ``(C, H, W)`` uint8 with C in {1, 3}, or ``box`` is not
                ``(4,)`` / ``(B, 4)``.
            BoxError: a box side is below ``min_box_size`` (3 pixels), is not finite, or the
                box lies outside the frame.
            TrackerError: ``box`` is ``None`` and the tracker cannot initialise itself, or more
                targets than ``max_targets`` are given.
        """
        self._check_frame(frame)
        h, w = int(frame.shape[-2]), int(frame.shape[-1])
        boxes = None
        if box is None:
            if not self.auto_init:
                raise TrackerError(
                    f"tracker {self.name!r} needs an initial box: init(frame, box=(x, y, w, h))"
                )
        else:
            # a tracker runs where its frames are: its boxes go there too
            try:
                boxes = torch.as_tensor(box)
            except (TypeError, ValueError, RuntimeError):  # a string, ragged lists, None inside
                raise ShapeError(
                    f"init box must be (4,) or (B, 4) numbers x, y, w, h, got "
                    f"{type(box).__name__} {box!r}"[:200]
                ) from None
            # a complex box lost its imaginary part with only a warning; bools were 0 / 1 pixels
            if boxes.is_complex() or boxes.dtype == torch.bool:
                raise ShapeError(
                    f"init box must be (4,) or (B, 4) real numbers x, y, w, h, got {boxes.dtype}"
                )
            boxes = boxes.to(frame.device, torch.float64)
            if boxes.ndim == 1:
                boxes = boxes.reshape(1, -1)
            if boxes.ndim != 2 or boxes.shape[-1] != 4:
                raise ShapeError(
                    f"init box must be (4,) or (B, 4) x, y, w, h, got {tuple(boxes.shape)}"
                )
            check_boxes(boxes, (h, w), name="init box", min_size=self.min_box_size)
            if self.max_targets is not None and boxes.shape[0] > self.max_targets:
                raise TrackerError(
                    f"tracker {self.name!r} follows at most {self.max_targets} target(s) per "
                    f"instance, got {boxes.shape[0]} boxes; create one tracker per target"
                )
        self.frame_size = (h, w)
        self._channels = int(frame.shape[0])
        state = self._init(frame, boxes)
        self._initialised = True
        return self._visible_in_frame(state)

    def update(self, frame: torch.Tensor) -> TrackState:
        """Track into the next frame ``(C, H, W)`` uint8; returns its :class:`TrackState`.

        Raises:
            TrackerError: called before :meth:`init`.
            ShapeError: ``frame`` has the wrong shape, dtype or size.
        """
        if not self._initialised:
            raise TrackerError(f"tracker {self.name!r}: update() called before init()")
        self._check_frame(frame)
        if self.frame_size is not None and tuple(frame.shape[-2:]) != self.frame_size:
            raise ShapeError(
                f"frame size changed from {self.frame_size} to {tuple(frame.shape[-2:])} "
                "(H, W) during tracking"
            )
        if int(frame.shape[0]) != self._channels:  # a gray frame after RGB ones was taken
            raise ShapeError(
                f"frame channels changed from {self._channels} to {int(frame.shape[0])} during "
                "tracking: give every frame in the first one's colour mode (1 gray, 3 RGB)"
            )
        return self._visible_in_frame(self._update(frame))

    def _visible_in_frame(self, state: TrackState) -> TrackState:
        """``state`` with ``visible`` cleared for boxes mostly outside the frame or not finite."""
        inside = inside_fraction(state.box.to(torch.float64), self.frame_size)
        ok = inside >= self.min_visible_inside
        vis = state.visible.to(torch.bool)
        if bool((vis & ~ok.to(vis.device)).any()):
            state = dataclasses.replace(state, visible=vis & ok.to(vis.device))
        return state

    # -- for subclasses ------------------------------------------------------------------------
    @abc.abstractmethod
    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        """Initialise on a checked ``frame (C, H, W)``; ``boxes (B, 4)`` float64 or ``None``."""

    @abc.abstractmethod
    def _update(self, frame: torch.Tensor) -> TrackState:
        """Track into a checked ``frame (C, H, W)``."""

    @staticmethod
    def _check_frame(frame: torch.Tensor) -> None:
        if not isinstance(frame, torch.Tensor):
            raise ShapeError(f"frame must be a torch.Tensor (C, H, W), got {type(frame).__name__}")
        if frame.ndim != 3 or frame.shape[0] not in (1, 3) or frame.dtype != torch.uint8:
            raise ShapeError(
                f"frame must be (C, H, W) uint8 with C = 1 or 3, got {tuple(frame.shape)} "
                f"{frame.dtype}"
            )
        if frame.shape[1] < 2 or frame.shape[2] < 2:
            raise ShapeError(f"frame is too small: {tuple(frame.shape)}")
        if frame.is_meta:  # no pixels to track: torch's 'item() cannot be called' came later
            raise ShapeError("frame is on the 'meta' device: it holds no pixels to track")


# ---------------------------------------------------------------------------------------------
# Registry
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackerInfo:
    """A registry entry: ``factory(**params) -> Tracker``; ``available()`` says whether it can
    be built here (e.g. opencv-contrib present) and ``requirement`` what to install if not."""

    name: str
    factory: Callable[..., Tracker]
    description: str = ""
    available: Callable[[], bool] = lambda: True
    requirement: str = ""

    @property
    def accepts_generator(self) -> bool:
        try:
            return "generator" in inspect.signature(self.factory).parameters
        except (TypeError, ValueError):
            return False


_REGISTRY: dict[str, TrackerInfo] = {}
_loaded = False


def register_tracker(
    name: str,
    factory: Callable[..., Tracker] | None = None,
    *,
    description: str = "",
    available: Callable[[], bool] | None = None,
    requirement: str = "",
):
    """Register ``factory`` (a Tracker class or a function returning one) under ``name``.

    Usable as a decorator (``@register_tracker("mil")``) or a call. Registering the same name
    twice with a different factory raises :class:`ConfigError`.
    """

    def deco(f: Callable[..., Tracker]) -> Callable[..., Tracker]:
        old = _REGISTRY.get(name)
        if old is not None and old.factory is not f:
            raise ConfigError(f"tracker name {name!r} is already registered by {old.factory}")
        _REGISTRY[name] = TrackerInfo(
            name=name,
            factory=f,
            description=description,
            available=available or (lambda: True),
            requirement=requirement,
        )
        return f

    return deco if factory is None else deco(factory)


def _load_builtins() -> None:
    global _loaded
    if _loaded:
        return
    _loaded = True
    for mod in BUILTIN_TRACKER_MODULES:
        try:
            importlib.import_module(mod)
        except Exception as exc:
            # One broken tracker module must not take the peers and the other trackers down
            # with it; say which one failed and why.
            warnings.warn(
                f"tracker module {mod} could not be imported ({type(exc).__name__}: {exc}); "
                "its trackers are unavailable",
                RuntimeWarning,
                stacklevel=3,
            )


def tracker_names() -> list[str]:
    """Every registered tracker name, sorted (available here or not)."""
    _load_builtins()
    return sorted(_REGISTRY)


def available_trackers() -> list[str]:
    """Registered tracker names that can be built in this environment, sorted."""
    _load_builtins()
    return sorted(n for n, info in _REGISTRY.items() if info.available())


def tracker_info(name: str) -> TrackerInfo:
    """The registry entry of ``name``; :class:`ConfigError` listing the names when unknown."""
    _load_builtins()
    info = _REGISTRY.get(name)
    if info is None:
        raise ConfigError(f"unknown tracker {name!r}; known trackers: {', '.join(tracker_names())}")
    return info


def create_tracker(name: str, **params: Any) -> Tracker:
    """Build the tracker registered as ``name`` with keyword ``params``.

    Raises:
        ConfigError: unknown name (the message lists the known ones), a tracker unavailable in
            this environment (the message says what to install), or parameters the factory
            does not accept.
    """
    info = tracker_info(name)
    if not info.available():
        raise ConfigError(
            f"tracker {name!r} is not available here"
            + (f": it needs {info.requirement}" if info.requirement else "")
        )
    try:
        sig = inspect.signature(info.factory)
    except (TypeError, ValueError):
        sig = None
    if sig is not None and not any(
        p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values()
    ):
        unknown = sorted(set(params) - set(sig.parameters))
        if unknown:
            valid = [p for p in sig.parameters if p != "self"]
            raise ConfigError(
                f"tracker {name!r} has no parameter(s) {', '.join(unknown)}; valid: "
                f"{', '.join(valid) or '(none)'}"
            )
    return info.factory(**params)


def _parse_value(v: str) -> Any:
    low = v.lower()
    if low in ("true", "false"):
        return low == "true"
    if low == "null":  # not "none": it is a real value of some options (e.g. adapt=none)
        return None
    from torchtrack.io.text import text_float, text_int

    # Python reads 1_0 as 10 and Arabic-Indic digits as numbers; a setting does not: the
    # text stays a string (refused where a number is expected)
    for cast in (text_int, text_float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def parse_tracker_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Split ``"name"`` or ``"name:key=value,key=value"`` into the name and its parameters
    (values become bool (true/false), int, float or None (null) where they parse as such,
    else strings; numbers are ASCII without ``_``: ``1_0`` stays the string ``'1_0'``).

    Example: ``parse_tracker_spec("adaptive-haar:adapt=none,particles=500")``.

    Raises:
        ConfigError: an item without ``=``, a key given twice, an empty name, or a ``:``
            with nothing after it.
    """
    name, colon, rest = spec.partition(":")
    name = name.strip()
    if not name:
        raise ConfigError(f"tracker spec {spec!r} has no name")
    if colon and not rest.strip():
        raise ConfigError(
            f"tracker spec {spec!r}: nothing after ':' (give name:key=value,... or the name alone)"
        )
    params: dict[str, Any] = {}
    if rest.strip():
        for item in rest.split(","):
            key, eq, val = item.partition("=")
            if not eq or not key.strip():
                raise ConfigError(
                    f"tracker spec {spec!r}: {item!r} is not key=value "
                    "(expected name:key=value,key=value)"
                )
            if key.strip() in params:
                raise ConfigError(f"tracker spec {spec!r}: {key.strip()!r} is given twice")
            params[key.strip()] = _parse_value(val.strip())
    return name, params
