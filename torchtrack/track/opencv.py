"""OpenCV trackers as peers behind the :class:`~torchtrack.track.base.Tracker` interface.

Registered names:

* ``mil``: ``cv2.TrackerMIL`` (in the main opencv-python(-headless) wheel).
* ``kcf``, ``csrt``: ``cv2.TrackerKCF`` / ``cv2.TrackerCSRT``, and ``mosse``, ``medianflow``,
  ``tld``, ``boosting``: ``cv2.legacy.Tracker*``. These need the ``peers`` extra
  (``opencv-contrib-python-headless``, which replaces the main wheel's ``cv2``);
  :func:`~torchtrack.track.base.create_tracker` says so when it is absent.
* ``camshift``: a CamShift baseline (hue histogram back-projection, ``cv2.CamShift``).

When an OpenCV tracker reports failure (``ok=False``) the wrapper keeps the last box, reports
``visible=False`` and confidence 0, and counts the frame in :attr:`OpenCVTracker.failures`.
Boxes returned by OpenCV are clipped to the frame. Frames are converted from ``(C, H, W)`` RGB
tensors to ``(H, W, 3)`` BGR arrays (gray frames are replicated to three channels).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import torch

from torchtrack.boxes import clip_boxes
from torchtrack.errors import BoxError, ConfigError, TrackerError
from torchtrack.io.video import to_numpy_bgr
from torchtrack.track.base import Tracker, TrackState, register_tracker

__all__ = ["CamShiftTracker", "OpenCVTracker", "has_contrib", "opencv_constructor"]

CONTRIB_REQUIREMENT = (
    "opencv-contrib-python-headless (pip install 'torchtrack[peers]'; it replaces the cv2 "
    "module of opencv-python-headless)"
)

# name -> (attribute paths tried in order, uses the legacy API, description)
_KINDS: dict[str, tuple[tuple[str, ...], bool, str]] = {
    "mil": (("TrackerMIL.create", "TrackerMIL_create"), False, "OpenCV TrackerMIL (main wheel)"),
    "kcf": (("TrackerKCF.create", "TrackerKCF_create"), False, "OpenCV TrackerKCF (contrib)"),
    "csrt": (("TrackerCSRT.create", "TrackerCSRT_create"), False, "OpenCV TrackerCSRT (contrib)"),
    "mosse": (("legacy.TrackerMOSSE_create",), True, "OpenCV legacy TrackerMOSSE (contrib)"),
    "medianflow": (
        ("legacy.TrackerMedianFlow_create",),
        True,
        "OpenCV legacy TrackerMedianFlow (contrib)",
    ),
    "tld": (("legacy.TrackerTLD_create",), True, "OpenCV legacy TrackerTLD (contrib)"),
    "boosting": (
        ("legacy.TrackerBoosting_create",),
        True,
        "OpenCV legacy TrackerBoosting (contrib)",
    ),
}


# name -> the smallest init box side (pixels, of the box's part inside the frame) the kind
# takes: OpenCV 5.0's TrackerMIL and legacy TrackerBoosting never return from init on boxes of
# 4x4 pixels or less (they draw random Haar features until one fits the patch), and no signal
# can stop them there. The other kinds start on 3x3 boxes (CSRT and MOSSE raise a cv2.error,
# a TrackerError here, on a 1x1 one).
_MIN_SIDE: dict[str, int] = {"mil": 5, "boosting": 5}


def _lookup(path: str) -> Callable | None:
    obj = cv2
    for part in path.split("."):
        obj = getattr(obj, part, None)
        if obj is None:
            return None
    return obj if callable(obj) else None


def opencv_constructor(kind: str) -> Callable | None:
    """The OpenCV factory of tracker ``kind`` in this cv2 build, or ``None`` if it lacks it."""
    if kind not in _KINDS:
        raise ConfigError(f"unknown OpenCV tracker kind {kind!r}; known: {', '.join(_KINDS)}")
    for path in _KINDS[kind][0]:
        f = _lookup(path)
        if f is not None:
            return f
    return None


def has_contrib() -> bool:
    """Whether the installed cv2 has the contrib trackers (``TrackerCSRT``)."""
    return opencv_constructor("csrt") is not None


def _box_from_cv(b, frame_size: tuple[int, int]) -> torch.Tensor:
    t = torch.tensor([[float(v) for v in b]], dtype=torch.float64)
    return clip_boxes(t, frame_size)


class OpenCVTracker(Tracker):
    """An OpenCV tracker (``kind`` in mil, kcf, csrt, mosse, medianflow, tld, boosting).

    ``mil`` and ``boosting`` refuse (:class:`BoxError`) an init box with less than 5 pixels a
    side inside the frame, before OpenCV sees it: OpenCV hangs on such boxes.

    Attributes:
        failures: number of ``update`` calls where OpenCV reported ``ok=False`` (or returned an
            empty box); on those frames the last box is kept and ``visible`` is False.
    """

    max_targets = 1

    def __init__(self, kind: str = "mil") -> None:
        super().__init__()
        ctor = opencv_constructor(kind)
        if ctor is None:
            raise ConfigError(
                f"OpenCV tracker {kind!r} is not in this cv2 build; it needs {CONTRIB_REQUIREMENT}"
            )
        self.kind = kind
        self.name = kind
        self._ctor = ctor
        self._legacy = _KINDS[kind][1]
        self._cv = None
        self._last: torch.Tensor | None = None
        self.failures = 0

    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        if boxes is None:  # pragma: no cover - guarded by Tracker.init (auto_init is False)
            raise TrackerError("OpenCV trackers need an initial box")
        img = to_numpy_bgr(frame)
        x, y, w, h = boxes[0].tolist()
        # Integer cv::Rect for every kind (round the corners, keep >= 1 pixel): the legacy
        # Boosting tracker of OpenCV 5.0 crashes (segfault) on fractional boxes.
        # The part of the box inside the frame: builds of OpenCV differ on boxes that reach
        # outside it (5.0's MIL throws std::bad_alloc, others crash the process).
        fh, fw = img.shape[:2]
        x1, y1 = min(max(round(x), 0), fw - 1), min(max(round(y), 0), fh - 1)
        x2, y2 = min(max(round(x + w), x1 + 1), fw), min(max(round(y + h), y1 + 1), fh)
        rect = (x1, y1, x2 - x1, y2 - y1)
        least = _MIN_SIDE.get(self.kind, 1)
        if min(rect[2:]) < least:
            raise BoxError(
                f"OpenCV {self.kind} needs an init box of at least {least}x{least} pixels "
                f"inside the frame, got {rect[2]}x{rect[3]} at ({x1}, {y1}); give a larger box "
                "or another tracker"
            )
        self._cv = self._ctor()
        try:
            ok = self._cv.init(img, rect)
        except cv2.error as exc:
            if self.kind == "mil" and "posSamples.empty()" in str(exc):
                why = (
                    "no room around the box to sample positives (MIL shifts it by a few pixels "
                    "and keeps only the shifts inside the frame); leave a few pixels between the "
                    "box and the frame's edges, or use another tracker"
                )
            else:
                why = _cv_error(exc)
            raise TrackerError(
                f"OpenCV {self.kind} failed to initialise on box {rect} in a "
                f"{img.shape[1]}x{img.shape[0]} frame: {why}"
            ) from None
        if ok is False:
            raise TrackerError(f"OpenCV {self.kind} failed to initialise on box {rect}")
        self._last = boxes[:1].clone()
        self.failures = 0
        return TrackState.single(self._last[0])

    def _update(self, frame: torch.Tensor) -> TrackState:
        try:
            ok, b = self._cv.update(to_numpy_bgr(frame))
        except cv2.error as exc:
            raise TrackerError(f"OpenCV {self.kind} failed on a frame: {_cv_error(exc)}") from None
        if ok and b is not None and b[2] > 0 and b[3] > 0:
            box = _box_from_cv(b, self.frame_size)
            if box[0, 2] > 0 and box[0, 3] > 0:
                self._last = box
                return TrackState.single(box[0], confidence=1.0, visible=True)
        self.failures += 1
        return TrackState.single(self._last[0], confidence=0.0, visible=False)


def _cv_error(exc: cv2.error) -> str:
    """What failed in ``exc``, without OpenCV's version banner and source path."""
    err, func = getattr(exc, "err", None), getattr(exc, "func", None)
    if err and func:
        return f"{err} (in OpenCV's {func})"
    return str(exc).strip()


class CamShiftTracker(Tracker):
    """CamShift baseline (Bradski 1998): back-project the target's hue histogram and let
    ``cv2.CamShift`` move and resize the window.

    The histogram is over hue (``bins`` bins) of the init box's pixels with saturation >= 60 and
    value in [32, 255] (the OpenCV sample's mask). When fewer than 10 % of the box's pixels pass
    that mask (grayscale or washed-out targets) the tracker uses a brightness histogram instead.
    ``visible`` is False when CamShift returns an empty window (the last box is kept) or when
    the mean back-projection inside the window falls below ``min_confidence``; ``confidence``
    is that mean back-projection in [0, 1].
    """

    name = "camshift"
    max_targets = 1

    def __init__(self, bins: int = 16, min_confidence: float = 0.05, max_iter: int = 10) -> None:
        super().__init__()
        if isinstance(bins, bool) or not isinstance(bins, int) or not 2 <= bins <= 256:
            raise ConfigError(f"camshift bins must be an integer in [2, 256], got {bins!r}")
        if not (  # a bool is no share: min_confidence=true ran at 1.0, never visible
            isinstance(min_confidence, (int, float))
            and not isinstance(min_confidence, bool)
            and 0 <= min_confidence <= 1
        ):
            raise ConfigError(
                f"camshift min_confidence must be in [0, 1] (a mean back-projection share), "
                f"got {min_confidence!r}"
            )
        if isinstance(max_iter, bool) or not isinstance(max_iter, int) or not 1 <= max_iter <= 1000:
            raise ConfigError(
                f"camshift max_iter must be an integer in [1, 1000], got {max_iter!r}"
            )
        self.bins = bins
        self.min_confidence = min_confidence
        self.max_iter = max_iter
        self.failures = 0

    def _planes(self, frame: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
        hsv = cv2.cvtColor(to_numpy_bgr(frame), cv2.COLOR_BGR2HSV)
        mask = cv2.inRange(hsv, (0, 60, 32), (180, 255, 255))
        return hsv, mask

    def _backproject(self, frame: torch.Tensor) -> np.ndarray:
        hsv, mask = self._planes(frame)
        if self._use_hue:
            bp = cv2.calcBackProject([hsv], [0], self._hist, [0, 180], 1)
            return cv2.bitwise_and(bp, bp, mask=mask)
        return cv2.calcBackProject([hsv], [2], self._hist, [0, 256], 1)

    def _init(self, frame: torch.Tensor, boxes: torch.Tensor | None) -> TrackState:
        if boxes is None:  # pragma: no cover - guarded by Tracker.init
            raise TrackerError("camshift needs an initial box")
        h_img, w_img = self.frame_size
        x, y, w, h = boxes[0].tolist()
        x1, y1 = max(0, int(np.floor(x))), max(0, int(np.floor(y)))
        x2, y2 = min(w_img, int(np.ceil(x + w))), min(h_img, int(np.ceil(y + h)))
        hsv, mask = self._planes(frame)
        roi, roi_mask = hsv[y1:y2, x1:x2], mask[y1:y2, x1:x2]
        self._use_hue = float((roi_mask > 0).mean()) >= 0.10
        if self._use_hue:
            hist = cv2.calcHist([roi], [0], roi_mask, [self.bins], [0, 180])
        else:
            hist = cv2.calcHist([roi], [2], None, [self.bins], [0, 256])
        cv2.normalize(hist, hist, 0, 255, cv2.NORM_MINMAX)
        self._hist = hist
        self._window = (x1, y1, max(1, x2 - x1), max(1, y2 - y1))
        self._last = boxes[:1].clone()
        self.failures = 0
        return TrackState.single(self._last[0])

    def _update(self, frame: torch.Tensor) -> TrackState:
        bp = self._backproject(frame)
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.max_iter, 1)
        _, window = cv2.CamShift(bp, self._window, crit)
        x, y, w, h = (int(v) for v in window)
        if w <= 0 or h <= 0:
            self.failures += 1
            return TrackState.single(self._last[0], confidence=0.0, visible=False)
        self._window = (x, y, w, h)
        box = _box_from_cv((x, y, w, h), self.frame_size)
        self._last = box
        conf = float(bp[y : y + h, x : x + w].mean()) / 255.0 if w * h > 0 else 0.0
        visible = conf >= self.min_confidence
        if not visible:
            self.failures += 1
        return TrackState.single(box[0], confidence=conf, visible=visible)


def _make(kind: str) -> Callable[[], OpenCVTracker]:
    def factory() -> OpenCVTracker:
        return OpenCVTracker(kind)

    factory.__name__ = f"opencv_{kind}"
    factory.__doc__ = f"Build the {_KINDS[kind][2]} tracker."
    return factory


for _kind, (_paths, _legacy, _desc) in _KINDS.items():
    register_tracker(
        _kind,
        _make(_kind),
        description=_desc,
        available=(lambda k=_kind: opencv_constructor(k) is not None),
        requirement="" if _kind == "mil" else CONTRIB_REQUIREMENT,
    )
register_tracker(
    "camshift", CamShiftTracker, description="CamShift on a hue histogram (OpenCV, main wheel)"
)
