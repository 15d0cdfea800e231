"""MOTChallenge files and sequences: ground truth, detections and tracking results.

A MOTChallenge file has one box per line, no header, comma separated (whitespace is accepted
too)::

    frame, id, bb_left, bb_top, bb_width, bb_height, conf, x, y, z      (MOT15, 10 columns)
    frame, id, bb_left, bb_top, bb_width, bb_height, conf, class, visibility   (MOT16+, 9)

Frames are 1-based; ``id`` is -1 in detection files; ``conf`` is the detector's score in
detection files, the tracker's confidence in results files and a 0/1 "consider" flag in ground
truth (0: ignored by the evaluation). Results files may stop after ``conf`` (7 columns) or even
after the box (6 columns, ``conf`` = 1).

Conventions (the package's, :mod:`torchtrack.boxes`, converted at this edge):

* :class:`MotRows` hold **0-based** frame indices (file frame - 1) and **0-based** boxes
  (file ``bb_left - 1``, ``bb_top - 1``: the MOTChallenge devkit numbers pixels from 1, as OTB
  does). :func:`write_mot` adds the 1 back, so ``write_mot(read_mot(f))`` reproduces ``f``'s
  boxes; ground truth, detections and results read here share one pixel grid.
* ``scale`` multiplies the 0-based ``x, y, w, h`` (PETS09-S2L1's ground truth is in 768x576
  coordinates for the 480x360 video: ``scale=0.625``).

Sequences (:func:`load_mot_sequence`):

* a **MOTChallenge folder**: ``seqinfo.ini``, ``gt/gt.txt``, ``img1/`` frames, ``det/det.txt``
  (public detections). A folder without ``img1/`` (e.g. ground truth shipped without frames)
  still loads: its length comes from ``seqinfo.ini``, and results files can be scored on it.
* a **video plus a ground-truth file**: the length and frame size come from the video. When the
  GT file sits in a MOTChallenge folder whose ``seqinfo.ini`` gives a different frame size, the
  scale is that ratio (``scale=None``); the name is then the folder's sequence name.
* a **folder of frames plus a ground-truth file** (image files directly in the folder, no
  ``seqinfo.ini`` nor ``img1/``: what ``torchtrack track`` reads): as a video, its length and
  frame size from the frames.

Every malformed row raises :class:`~torchtrack.errors.MotFormatError` naming the file and the
line: a wrong number of columns, a non-number, a non-finite value, a frame below 1 or beyond the
sequence, a non-integer frame or id, a box of zero or negative size or with a value beyond
``MAX_COORD`` pixels, an identity given twice in one frame. Scales lie in ``SCALE_RANGE``.

Example::

    seq = load_mot_sequence("MOT15/train/TUD-Stadtmitte")
    det = seq.detections()                      # MotRows of det/det.txt
    for t, rows in enumerate(det.split(seq.n_frames)):
        boxes = torch.from_numpy(det.boxes[rows])        # (K_t, 4) x, y, w, h of frame t
    write_mot("out.txt", MotRows.from_arrays(frames, ids, boxes, conf))
"""

from __future__ import annotations

import configparser
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from torchtrack.errors import MotFormatError, SequenceError, ShapeError, VideoError
from torchtrack.io.atomic import atomic_write
from torchtrack.io.text import text_float
from torchtrack.io.video import (
    IMAGE_EXTENSIONS,
    VIDEO_EXTENSIONS,
    FrameSource,
    list_image_files,
)

__all__ = [
    "MotRows",
    "MotSequence",
    "SeqInfo",
    "find_mot_sequences",
    "format_mot_row",
    "is_frame_folder",
    "is_mot_folder",
    "load_mot_sequence",
    "read_mot",
    "read_seqinfo",
    "write_mot",
]

Kind = Literal["gt", "det", "results"]
_SPLIT = re.compile(r"\s*,\s*|\s+")
_KIND_WORD = {"gt": "ground-truth", "det": "detections", "results": "results"}
_MIN_COLS = {"gt": 7, "det": 6, "results": 6}
_MAX_COLS = 10


def _as_numpy(a, dtype, name: str) -> np.ndarray:
    if hasattr(a, "detach"):  # torch tensor
        a = a.detach().cpu().numpy()
    try:
        return np.asarray(a, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise ShapeError(f"{name} cannot be converted to {np.dtype(dtype).name}: {exc}") from None


@dataclass(frozen=True)
class MotRows:
    """Boxes of a MOTChallenge file, one entry per row (module doc for the conventions).

    Attributes:
        frames: ``(K,)`` int64, 0-based frame index (file frame - 1).
        ids: ``(K,)`` int64 identities (-1 in detection files).
        boxes: ``(K, 4)`` float64 ``x, y, w, h`` in pixels, 0-based, scaled.
        conf: ``(K,)`` float64: detector score, tracker confidence, or the GT's 0/1 flag.
        extra: ``(K, E)`` float64 columns after ``conf`` (world coordinates, class, ...).
        lines: ``(K,)`` int64 line numbers in ``path`` (1-based), ``-1`` for built rows.
        path: the file read, else ``None``.

    ``torch.from_numpy(rows.boxes)`` gives a tensor without a copy.
    """

    frames: np.ndarray
    ids: np.ndarray
    boxes: np.ndarray
    conf: np.ndarray
    extra: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    lines: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    path: Path | None = None

    def __post_init__(self) -> None:
        k = len(self.frames)
        if self.boxes.shape != (k, 4):
            raise ShapeError(f"boxes must have shape ({k}, 4), got {self.boxes.shape}")
        for name in ("ids", "conf"):
            if getattr(self, name).shape != (k,):
                raise ShapeError(f"{name} must have shape ({k},), got {getattr(self, name).shape}")
        if self.extra.shape[0] != k:
            object.__setattr__(self, "extra", np.zeros((k, 0)))
        if self.lines.shape != (k,):
            object.__setattr__(self, "lines", np.full(k, -1, np.int64))

    @classmethod
    def from_arrays(cls, frames, ids, boxes, conf=None) -> MotRows:
        """Rows from arrays or tensors (what a tracker produces, ready for :func:`write_mot`).

        Args:
            frames: ``(K,)`` 0-based frame indices.
            ids: ``(K,)`` identities (>= 0 for tracks; -1 for detections).
            boxes: ``(K, 4)`` ``x, y, w, h``, 0-based pixels.
            conf: ``(K,)`` confidences; default 1.

        Raises:
            ShapeError: inconsistent lengths or shapes.
        """
        f = _as_numpy(frames, np.int64, "frames").reshape(-1)
        b = _as_numpy(boxes, np.float64, "boxes")
        if not len(f):
            b = np.zeros((0, 4))
        elif b.shape == (4,) and len(f) == 1:  # one row's box
            b = b.reshape(1, 4)
        elif b.ndim != 2 or b.shape[1] != 4:
            raise ShapeError(f"boxes must have shape ({len(f)}, 4), got {b.shape}")
        i = _as_numpy(ids, np.int64, "ids").reshape(-1)
        c = np.ones(len(f)) if conf is None else _as_numpy(conf, np.float64, "conf").reshape(-1)
        return cls(frames=f, ids=i, boxes=b, conf=c)

    @classmethod
    def empty(cls) -> MotRows:
        """No rows (an empty tracker)."""
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros(0))

    def __len__(self) -> int:
        return len(self.frames)

    def select(self, index) -> MotRows:
        """The rows at ``index`` (a boolean mask or integer indices), in that order."""
        return MotRows(
            frames=self.frames[index],
            ids=self.ids[index],
            boxes=self.boxes[index],
            conf=self.conf[index],
            extra=self.extra[index],
            lines=self.lines[index],
            path=self.path,
        )

    def split(self, n_frames: int) -> list[np.ndarray]:
        """Row indices of each frame: ``out[t]`` indexes the rows of frame ``t`` (0-based), in
        file order; frames without rows get an empty array. Rows at or beyond ``n_frames`` are
        left out (:func:`read_mot` with ``n_frames`` rejects them)."""
        order = np.argsort(self.frames, kind="stable")
        f = self.frames[order]
        starts = np.searchsorted(f, np.arange(n_frames + 1))
        return [order[starts[t] : starts[t + 1]] for t in range(n_frames)]

    def scaled(self, scale: float) -> MotRows:
        """The same rows with boxes multiplied by ``scale``."""
        return MotRows(
            self.frames, self.ids, self.boxes * scale, self.conf, self.extra, self.lines, self.path
        )


# ---------------------------------------------------------------------------------------------
# Reading and writing files
# ---------------------------------------------------------------------------------------------
#: the largest identity a MOTChallenge row may carry (2^31 - 1, as the devkits' integers)
MAX_ID = 2**31 - 1
#: the most frames a sequence may have (about four days at 25 fps): a larger ``seqLength``
#: or frame number is a typo that would size the scoring's per-frame tables beyond any memory
MAX_SEQ_LENGTH = 10_000_000
#: the largest box coordinate or size a file may give, in pixels (frames are at most some ten
#: thousand pixels wide): beyond it a value is a typo whose areas overflow in the scoring
MAX_COORD = 1e6
#: the range of a ground-truth scale (PETS09-S2L1 uses 0.625): outside it the boxes are a typo
#: away from any frame, and 1e308 overflowed them to inf
SCALE_RANGE = (1e-3, 1e3)


def _check_scale(scale, what: str = "scale") -> float:
    """``scale`` as a float within :data:`SCALE_RANGE`, else :class:`SequenceError` (a
    ``ValueError``)."""
    lo, hi = SCALE_RANGE
    if not (
        isinstance(scale, (int, float))
        and not isinstance(scale, bool)
        and math.isfinite(scale)
        and lo <= scale <= hi
    ):
        raise SequenceError(f"{what} must be a number in [{lo:g}, {hi:g}], got {scale!r}")
    return float(scale)


def _fail(path: Path, no: int, msg: str, line: str | None = None) -> MotFormatError:
    shown = f": {line.strip()[:80]!r}" if line is not None else ""
    return MotFormatError(f"{path} line {no}: {msg}{shown}")


def read_mot(
    path: str | os.PathLike,
    scale: float = 1.0,
    n_frames: int | None = None,
    *,
    kind: Kind = "results",
) -> MotRows:
    """Read a MOTChallenge file (module doc for the format and conventions).

    Args:
        path: the file. An empty file is valid and gives no rows (an empty tracker).
        scale: multiplies the boxes (after the shift to 0-based pixels).
        n_frames: the sequence's length; a row with a frame beyond it is an error.
        kind: ``"gt"`` (at least 7 columns: ``conf`` is the consider flag; ids >= 0, unique
            per frame), ``"results"`` (ids >= 0, unique per frame) or ``"det"`` (ids ignored).

    Returns:
        :class:`MotRows` in file order.

    Raises:
        MotFormatError: unreadable file or a malformed row (file and line in the message).
        SequenceError: ``scale`` outside :data:`SCALE_RANGE`.
        ValueError: unknown ``kind``.
    """
    if kind not in _MIN_COLS:
        raise ValueError(f"kind must be 'gt', 'det' or 'results', got {kind!r}")
    _check_scale(scale)
    p = Path(path)
    word = _KIND_WORD[kind]
    try:
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise MotFormatError(f"{word} file {p} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MotFormatError(f"{word} file {p} cannot be read as text: {exc}") from None
    rows: list[list[float]] = []
    line_nos: list[int] = []
    n_cols = None
    first_line = 0
    lines = text.splitlines()
    for no, line in enumerate(lines, start=1):
        s = line.strip()
        if not s:
            continue
        parts = _SPLIT.split(s)
        try:
            vals = [text_float(v) for v in parts]
        except ValueError:
            raise _fail(p, no, f"not a row of numbers ({word} file)", line) from None
        if n_cols is None:
            if not _MIN_COLS[kind] <= len(vals) <= _MAX_COLS:
                raise _fail(
                    p,
                    no,
                    f"{len(vals)} columns; a {word} file has {_MIN_COLS[kind]} to {_MAX_COLS} "
                    "(frame, id, bb_left, bb_top, bb_width, bb_height"
                    + (", conf" if kind == "gt" else "[, conf]")
                    + ", ...)",
                    line,
                )
            n_cols, first_line = len(vals), no
        elif len(vals) != n_cols:
            raise _fail(p, no, f"{len(vals)} columns, line {first_line} has {n_cols}", line)
        if not all(math.isfinite(v) for v in vals):
            raise _fail(p, no, "a value is not finite", line)
        rows.append(vals)
        line_nos.append(no)
    if not rows:
        return MotRows(
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros((0, 4)),
            np.zeros(0),
            np.zeros((0, 0)),
            np.zeros(0, np.int64),
            p,
        )
    a = np.asarray(rows, dtype=np.float64)
    nos = np.asarray(line_nos, dtype=np.int64)

    def check(bad: np.ndarray, msg) -> None:
        if bad.any():
            k = int(np.argmax(bad))
            raise _fail(p, int(nos[k]), msg(k), lines[nos[k] - 1])

    check(a[:, 0] != np.round(a[:, 0]), lambda k: "the frame number is not an integer")
    check(a[:, 0] < 1, lambda k: f"frame {a[k, 0]:g}: frames are numbered from 1")
    check(
        a[:, 0] > MAX_SEQ_LENGTH,
        lambda k: f"frame {a[k, 0]:g} is beyond any sequence (at most {MAX_SEQ_LENGTH} frames)",
    )
    if n_frames is not None:
        check(
            a[:, 0] > n_frames,
            lambda k: f"frame {int(a[k, 0])} is beyond the sequence's {n_frames} frames",
        )
    check(a[:, 1] != np.round(a[:, 1]), lambda k: "the id is not an integer")
    check(
        np.abs(a[:, 1]) > MAX_ID,
        lambda k: f"id {a[k, 1]:g} is out of range (identities are at most {MAX_ID})",
    )
    if kind != "det":
        check(a[:, 1] < 0, lambda k: f"id {int(a[k, 1])}: identities must be >= 0")
    check(
        (a[:, 4] <= 0) | (a[:, 5] <= 0),
        lambda k: f"box of size {a[k, 4]:g} x {a[k, 5]:g}: width and height must be > 0",
    )
    check(
        (np.abs(a[:, 2:6]) > MAX_COORD).any(axis=1),
        lambda k: (
            f"box {', '.join(f'{v:g}' for v in a[k, 2:6])} (x, y, w, h) has a value "
            f"beyond +-{MAX_COORD:g} pixels"
        ),
    )
    frames = a[:, 0].astype(np.int64) - 1
    ids = a[:, 1].astype(np.int64)
    if kind != "det":
        key = frames * (int(ids.max()) + 1) + ids
        order = np.argsort(key, kind="stable")
        dup = np.nonzero(key[order][1:] == key[order][:-1])[0]
        if len(dup):
            k0, k1 = int(order[dup[0]]), int(order[dup[0] + 1])
            raise _fail(
                p,
                int(nos[k1]),
                f"id {ids[k1]} appears twice in frame {frames[k1] + 1} "
                f"(also on line {int(nos[k0])})",
                lines[nos[k1] - 1],
            )
    boxes = a[:, 2:6].copy()
    boxes[:, :2] -= 1.0  # MOTChallenge pixels are numbered from 1
    conf = a[:, 6].copy() if n_cols >= 7 else np.ones(len(a))
    return MotRows(
        frames=frames,
        ids=ids,
        boxes=boxes * scale if scale != 1.0 else boxes,
        conf=conf,
        extra=a[:, 7:].copy(),
        lines=nos,
        path=p,
    )


def write_mot(path: str | os.PathLike, rows: MotRows, *, kind: Kind = "results") -> None:
    """Write ``rows`` as a MOTChallenge results file (or ``kind`` ``"gt"`` / ``"det"``, as
    :func:`read_mot` reads them), atomically.

    Lines are ``frame,id,x,y,w,h,conf,-1,-1,-1`` (1-based frame and pixels, boxes with three
    decimals), sorted by frame then id. No rows give an empty file (a valid, empty tracker).

    Raises:
        ValueError: what :func:`read_mot` would refuse in a results file: a non-finite box or
            confidence, a box without area or beyond ``MAX_COORD`` pixels, a negative frame
            index or identity, or an identity twice in one frame.
    """
    order = np.lexsort((rows.ids, rows.frames))
    if len(rows):
        if not (np.isfinite(rows.boxes).all() and np.isfinite(rows.conf).all()):
            raise ValueError("write_mot: boxes and confidences must be finite")
        if rows.frames.min() < 0:
            raise ValueError("write_mot: frame indices are 0-based and must be >= 0")
        if kind not in _MIN_COLS:
            raise ValueError(f"kind must be 'gt', 'det' or 'results', got {kind!r}")
        if kind != "det" and rows.ids.min() < 0:
            raise ValueError(f"write_mot: identities must be >= 0 in a {kind} file")
        if not ((rows.boxes[:, 2] > 0) & (rows.boxes[:, 3] > 0)).all():
            raise ValueError("write_mot: box widths and heights must be > 0")
        if (np.abs(rows.boxes) > MAX_COORD - 1).any():
            raise ValueError(f"write_mot: box values must lie within +-{MAX_COORD:g} pixels")
        f, i = rows.frames[order], rows.ids[order]
        twice = np.nonzero((f[1:] == f[:-1]) & (i[1:] == i[:-1]))[0]
        if len(twice) and kind != "det":
            k = int(twice[0])
            raise ValueError(f"write_mot: id {i[k]} appears twice in frame {f[k] + 1}")
    with atomic_write(path, "w", encoding="utf-8", newline="\n") as f:
        for k in order:
            f.write(format_mot_row(rows.frames[k], rows.ids[k], rows.boxes[k], rows.conf[k]))


def format_mot_row(frame: int, ident: int, box, conf: float) -> str:
    """One results line ``frame,id,x,y,w,h,conf,-1,-1,-1`` from a 0-based ``frame`` and a
    0-based ``box`` (x, y, w, h): 1-based in the file, boxes with three decimals."""
    x, y, w, h = (float(v) for v in box)
    return (
        f"{int(frame) + 1},{int(ident)},{x + 1:.3f},{y + 1:.3f},{w:.3f},{h:.3f},"
        f"{float(conf):.6g},-1,-1,-1\n"
    )


# ---------------------------------------------------------------------------------------------
# seqinfo.ini
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SeqInfo:
    """The ``[Sequence]`` section of a MOTChallenge ``seqinfo.ini``."""

    name: str
    seq_length: int
    im_dir: str = "img1"
    frame_rate: float | None = None
    im_width: int | None = None
    im_height: int | None = None
    #: the frames' extension (``imExt``, e.g. ``".jpg"``); ``None`` when not given (every image
    #: file of ``im_dir`` is then a frame)
    im_ext: str | None = None


#: a number as written in a file: ASCII digits, an optional fraction and exponent (Python's
#: float() also reads '1_0', Arabic-Indic digits, 'inf' and 'nan')
_NUMBER = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?", re.ASCII)


def read_seqinfo(path: str | os.PathLike) -> SeqInfo:
    """Read a ``seqinfo.ini``.

    Numbers are written with ASCII digits; ``seqLength``, ``imWidth`` and ``imHeight`` are
    whole numbers (``6`` or ``6.0``), ``frameRate`` a finite number; all are > 0. ``imExt``,
    when given, is an image file extension with its dot (``.jpg``).

    Raises:
        MotFormatError: unreadable, no ``[Sequence]`` section, a missing ``seqLength``, a
            value that is not a number, not finite, not whole where a count is expected or not
            > 0, or an ``imExt`` that is not an image file extension.
    """
    p = Path(path)
    cp = configparser.ConfigParser(interpolation=None)  # values as written ('%' included)
    try:
        with open(p, encoding="utf-8-sig") as f:
            cp.read_file(f)
    except OSError as exc:
        raise MotFormatError(f"{p} cannot be read: {exc}") from None
    except UnicodeDecodeError:
        raise MotFormatError(f"{p} is not a text file (not UTF-8)") from None
    except configparser.MissingSectionHeaderError as exc:
        raise MotFormatError(
            f"{p} is not a valid ini file: line {exc.lineno} {exc.line.strip()!r} comes before "
            "any section header (a seqinfo.ini starts with [Sequence])"
        ) from None
    except configparser.Error as exc:  # one line: configparser's own message spans several
        raise MotFormatError(f"{p} is not a valid ini file: {' '.join(str(exc).split())}") from None
    if not cp.has_section("Sequence"):
        raise MotFormatError(f"{p} has no [Sequence] section")
    sec = cp["Sequence"]

    def num(key: str, cast, required: bool = False):
        if key not in sec:
            if required:
                raise MotFormatError(f"{p}: [Sequence] has no {key}")
            return None
        text = sec[key].strip()
        try:
            v = float(text)
        except ValueError:
            v = None
        if v is None or (_NUMBER.fullmatch(text) is None and math.isfinite(v)):
            # int() read '6.0' as 'not a number'; float() reads '1_0' and other digits
            raise MotFormatError(f"{p}: {key}={sec[key]!r} is not a number")
        if cast is int:
            if not (math.isfinite(v) and v.is_integer()):
                raise MotFormatError(f"{p}: {key}={sec[key]!r} must be a whole number")
            v = int(v)
        elif not math.isfinite(v) or not v > 0:  # frameRate=inf was taken
            raise MotFormatError(f"{p}: {key}={sec[key]!r} must be a finite number > 0")
        if not v > 0:
            raise MotFormatError(f"{p}: {key}={sec[key]!r} must be > 0")
        return v

    def extension() -> str | None:
        if "imExt" not in sec:
            return None
        v = sec["imExt"].strip()
        if v.lower() not in IMAGE_EXTENSIONS:
            raise MotFormatError(
                f"{p}: imExt={v!r} is not an image file extension (one of "
                f"{', '.join(sorted(IMAGE_EXTENSIONS))}, with its dot)"
            )
        return v

    def component(key: str, default: str) -> str:
        # used as a file or folder name beside the sequence (results are <name>.txt): one
        # plain path component, so nothing is read or written outside the folders given
        v = sec.get(key, default).strip()
        if not v or v in (".", "..") or any(c in v for c in "/\\\0"):
            raise MotFormatError(
                f"{p}: {key}={v!r} must be one plain file name (no path separators, not "
                "empty, not '.' or '..')"
            )
        return v

    length = num("seqLength", int, required=True)
    if length > MAX_SEQ_LENGTH:
        raise MotFormatError(
            f"{p}: seqLength={length} is more than {MAX_SEQ_LENGTH} frames (the count of the "
            "sequence's frames, not their size)"
        )
    return SeqInfo(
        name=component("name", p.parent.name),
        seq_length=length,
        im_dir=component("imDir", "img1"),
        frame_rate=num("frameRate", float),
        im_width=num("imWidth", int),
        im_height=num("imHeight", int),
        im_ext=extension(),
    )


# ---------------------------------------------------------------------------------------------
# Sequences
# ---------------------------------------------------------------------------------------------
@dataclass
class MotSequence:
    """A multi-target sequence: frames (or at least their number) and ground truth.

    Attributes:
        name: the sequence name (``seqinfo.ini``'s, else the folder or video stem); results
            files in a folder are looked up as ``<name>.txt``.
        gt: ground-truth :class:`MotRows`, scaled to the frames' pixels.
        n_frames: number of frames.
        gt_path: the ground-truth file.
        scale: the factor applied to the ground truth (and to :meth:`detections`).
        frames: image files in order (MOTChallenge ``img1/``, or a folder of frames given
            with its ground truth), else ``None``.
        video: the video file, else ``None``.
        det_path: the public detections (``det/det.txt``) when present.
        width, height: frame size in pixels when known.
        frame_rate: frames per second when known.
        im_dir: the frames' folder a MOTChallenge folder names (``img1/`` or ``seqinfo.ini``'s
            ``imDir``), whether or not it exists; ``None`` for a video.
    """

    name: str
    gt: MotRows
    n_frames: int
    gt_path: Path
    scale: float = 1.0
    frames: list[Path] | None = None
    video: Path | None = None
    det_path: Path | None = None
    width: int | None = None
    height: int | None = None
    frame_rate: float | None = None
    im_dir: Path | None = None

    @property
    def source(self) -> Path | list[Path] | None:
        """What to read the frames from: the video, the frame list, or ``None``."""
        return self.video if self.video is not None else self.frames

    def open(self, color: str = "rgb") -> FrameSource:
        """The frames as a :class:`~torchtrack.io.video.FrameSource`.

        Raises:
            VideoError: the sequence has no frames here (ground truth only).
        """
        if self.source is None:
            # the folder looked for: seqinfo.ini's imDir may name another than img1/ (which
            # the message named even when it was there)
            where = f"{self.im_dir}/" if self.im_dir is not None else "img1/"
            raise VideoError(
                f"sequence {self.name} has no frames here (no {where} folder and no video)"
            )
        return FrameSource(self.source, color=color)

    def detections(self, path: str | os.PathLike | None = None) -> MotRows:
        """Detections in MOT format (default: the public ``det/det.txt``), scaled like the
        ground truth and checked against the sequence's length.

        Raises:
            MotFormatError: no such file, or a malformed row.
        """
        p = path if path is not None else self.det_path
        if p is None:
            raise MotFormatError(f"sequence {self.name} has no det/det.txt")
        return read_mot(p, self.scale, self.n_frames, kind="det")


def is_mot_folder(path: str | os.PathLike) -> bool:
    """A folder with ``gt/gt.txt`` and ``seqinfo.ini`` or ``img1/``."""
    d = Path(path)
    return (d / "gt" / "gt.txt").is_file() and (
        (d / "seqinfo.ini").is_file() or (d / "img1").is_dir()
    )


def _resolve_scale(scale: float | None, what: str = "the ground-truth scale") -> float:
    if scale is None:
        return 1.0
    return _check_scale(scale, what)


def load_mot_sequence(
    path: str | os.PathLike,
    gt: str | os.PathLike | None = None,
    scale: float | None = None,
) -> MotSequence:
    """Load a MOTChallenge folder, or a video or a folder of frames plus its ground-truth file
    (module doc).

    Args:
        path: a MOTChallenge folder, a video file, or a folder of frames (images directly in
            it, no ``seqinfo.ini`` nor ``img1/``: :func:`is_frame_folder`) with ``gt``.
        gt: the ground-truth file (required for a video and a frame folder; default
            ``gt/gt.txt`` of a MOTChallenge folder).
        scale: factor for the ground truth; ``None``: 1 for a MOTChallenge folder, and for a
            video or a frame folder the ratio of its width to the ``imWidth`` of the
            ``seqinfo.ini`` next to the GT (``<seq>/seqinfo.ini`` for ``<seq>/gt/gt.txt``), 1
            when there is none.

    Raises:
        SequenceError: neither a MOTChallenge folder nor a video, a video without ``gt``, a
            frame count that disagrees with ``seqinfo.ini``, frame sizes of a different shape,
            a folder's first frame of another size than ``seqinfo.ini``'s ``imWidth`` x
            ``imHeight`` (unless ``scale`` is given).
        MotFormatError: a malformed ground-truth file or ``seqinfo.ini``, GT rows beyond the
            sequence's frames.
        VideoError: the video cannot be opened.
    """
    p = Path(path)
    if p.is_dir() and gt is not None and is_frame_folder(p):
        return _load_frames(p, Path(gt), scale)
    if p.is_dir():
        return _load_folder(p, gt, _resolve_scale(scale), check_size=scale is None)
    if p.is_file() and p.suffix.lower() in VIDEO_EXTENSIONS:
        if gt is None:
            raise SequenceError(
                f"{p} is a video: give its ground-truth file (MOTChallenge gt.txt) as well"
            )
        return _load_video(p, Path(gt), scale)
    if not p.exists():
        raise SequenceError(f"MOT sequence {p} does not exist")
    raise SequenceError(
        f"{p} is neither a MOTChallenge folder (seqinfo.ini, gt/gt.txt, img1/) nor a video "
        f"({', '.join(sorted(VIDEO_EXTENSIONS))})"
    )


def _load_folder(
    d: Path, gt: str | os.PathLike | None, scale: float, check_size: bool = True
) -> MotSequence:
    info = read_seqinfo(d / "seqinfo.ini") if (d / "seqinfo.ini").is_file() else None
    img_dir = d / (info.im_dir if info else "img1")
    frames = list_image_files(img_dir) if img_dir.is_dir() else None
    if frames is not None and info is not None and info.im_ext is not None:
        frames = _frames_of_extension(frames, info.im_ext, img_dir, d / "seqinfo.ini")
    if info is None and frames is None:
        raise SequenceError(
            f"{d} is not a MOTChallenge folder: it has neither seqinfo.ini nor an img1/ folder, "
            "so its number of frames is unknown"
        )
    if info is not None and frames is not None and len(frames) != info.seq_length:
        raise SequenceError(
            f"{img_dir} holds {len(frames)} frames but {d / 'seqinfo.ini'} says "
            f"seqLength={info.seq_length}"
        )
    if check_size and info is not None and frames and info.im_width and info.im_height:
        _check_frame_size(frames[0], info, d / "seqinfo.ini")
    gt_path = Path(gt) if gt is not None else d / "gt" / "gt.txt"
    if not gt_path.is_file():  # a folder was reported as not existing
        why = "is a folder, not a file" if gt_path.is_dir() else "does not exist"
        raise SequenceError(f"{d} has no ground truth ({gt_path} {why})")
    n = info.seq_length if info else len(frames)
    det = d / "det" / "det.txt"
    return MotSequence(
        name=info.name if info else d.name,
        gt=read_mot(gt_path, scale, n, kind="gt"),
        n_frames=n,
        gt_path=gt_path,
        scale=scale,
        frames=frames,
        det_path=det if det.is_file() else None,
        width=None if info is None else info.im_width,
        height=None if info is None else info.im_height,
        frame_rate=None if info is None else info.frame_rate,
        im_dir=img_dir,
    )


def _frames_of_extension(frames: list[Path], ext: str, img_dir: Path, ini: Path) -> list[Path]:
    """The frames whose extension is ``seqinfo.ini``'s ``imExt`` (any case): what the
    MOTChallenge devkit reads (it was ignored: frames of another extension were taken, and a
    folder with a copy of every frame in another format was 'twice seqLength').

    Raises:
        SequenceError: no frame has that extension.
    """
    kept = [f for f in frames if f.suffix.lower() == ext.lower()]
    if not kept:
        from collections import Counter

        held = Counter(f.suffix.lower() for f in frames)
        listed = ", ".join(f"{n} {e} file(s)" for e, n in sorted(held.items()))
        raise SequenceError(
            f"{img_dir} holds no {ext} frame (the extension {ini} gives, imExt={ext}): it holds "
            f"{listed}"
        )
    return kept


def _check_frame_size(first: Path, info: SeqInfo, ini: Path) -> None:
    """:class:`SequenceError` when the first frame's size is not ``seqinfo.ini``'s ``imWidth``
    x ``imHeight``: the ground truth is in those pixels, so frames resized since (half size
    for speed) were scored against boxes twice their size, with no warning (the warnings
    measure the frames by ``seqinfo.ini``). An unreadable first frame is left to the reader;
    an explicit ``scale`` skips the check."""
    from torchtrack.errors import DataError
    from torchtrack.io.video import decode_image

    try:
        img = decode_image(first)
    except DataError:
        return
    h, w = int(img.shape[0]), int(img.shape[1])
    if (w, h) != (info.im_width, info.im_height):
        raise SequenceError(
            f"{first} is {w}x{h} but {ini} says imWidth={info.im_width} "
            f"imHeight={info.im_height}, the ground truth's pixels (frames resized since?): give "
            "the ground-truth scale explicitly (eval --gt-scale)"
        )


def is_frame_folder(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder of frames rather than a MOTChallenge folder: it holds image
    files itself and has neither ``seqinfo.ini`` nor ``img1/`` (what ``torchtrack track``
    reads as a video)."""
    p = Path(path)
    if not p.is_dir() or (p / "seqinfo.ini").is_file() or (p / "img1").is_dir():
        return False
    try:
        return bool(list_image_files(p))
    except VideoError:  # no image file in it
        return False


def _load_frames(folder: Path, gt_path: Path, scale: float | None) -> MotSequence:
    """A folder of frames and its ground-truth file, as :func:`_load_video` loads a video."""
    from torchtrack.errors import DataError
    from torchtrack.io.video import decode_image

    frames = list_image_files(folder)
    try:
        img = decode_image(frames[0])
        h, w = int(img.shape[0]), int(img.shape[1])
    except DataError:  # the reader reports it; no size to scale by
        h = w = 0
    return _with_gt(folder, folder.name, gt_path, scale, len(frames), w, h, None, frames=frames)


def _load_video(video: Path, gt_path: Path, scale: float | None) -> MotSequence:
    import cv2

    cap = cv2.VideoCapture(str(video))
    try:
        if not cap.isOpened():
            raise VideoError(f"video file {video} cannot be opened (unknown or broken format)")
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
    finally:
        cap.release()
    if n <= 0:
        raise VideoError(f"video file {video} announces no frames")
    return _with_gt(video, video.stem, gt_path, scale, n, w, h, fps, video=video)


def _with_gt(
    src: Path,
    stem: str,
    gt_path: Path,
    scale: float | None,
    n: int,
    w: int,
    h: int,
    fps: float | None,
    *,
    video: Path | None = None,
    frames: list[Path] | None = None,
) -> MotSequence:
    """A video's or a frame folder's :class:`MotSequence` with the ground truth ``gt_path``
    (scaled by ``scale``, or by the ``seqinfo.ini`` beside it: :func:`load_mot_sequence`)."""
    if not gt_path.is_file():  # a folder was reported as not existing
        why = "is a folder, not a file" if gt_path.is_dir() else "does not exist"
        raise SequenceError(f"ground-truth file {gt_path} {why}")
    seq_dir = gt_path.parent.parent if gt_path.parent.name == "gt" else None
    ini = seq_dir / "seqinfo.ini" if seq_dir is not None else None
    info = read_seqinfo(ini) if ini is not None and ini.is_file() else None
    if info is not None and info.seq_length != n:
        raise SequenceError(
            f"{src} has {n} frames but {ini} says seqLength={info.seq_length}: the ground "
            "truth belongs to another video"
        )
    what = "the ground-truth scale"
    if scale is None:
        scale = 1.0
        if info is not None and info.im_width and info.im_height and w > 0:
            sx, sy = w / info.im_width, h / info.im_height
            if abs(sx - sy) > 0.01 * max(sx, sy):
                raise SequenceError(
                    f"{src} is {w}x{h} but {ini} describes {info.im_width}x{info.im_height} "
                    "frames, another aspect ratio: give the ground-truth scale explicitly"
                )
            scale = sx
            what = f"the ground-truth scale {w} / imWidth={info.im_width} of {ini}"
    scale = _resolve_scale(scale, what)
    return MotSequence(
        name=info.name if info is not None else stem,
        gt=read_mot(gt_path, scale, n, kind="gt"),
        n_frames=n,
        gt_path=gt_path,
        scale=scale,
        frames=frames,
        video=video,
        det_path=None,
        width=w or None,
        height=h or None,
        frame_rate=fps,
    )


def find_mot_sequences(path: str | os.PathLike, max_depth: int = 2) -> list[Path]:
    """MOTChallenge folders at ``path`` or below it (``MOT15/train`` holds one per sequence),
    in sorted order; ``[path]`` itself when it is one."""
    root = Path(path)
    if is_mot_folder(root):
        return [root]
    found: list[Path] = []
    if root.is_dir() and max_depth > 0:
        for sub in sorted(q for q in root.iterdir() if q.is_dir()):
            found.extend(find_mot_sequences(sub, max_depth - 1))
    return found
