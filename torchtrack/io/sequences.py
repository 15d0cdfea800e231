"""Tracking sequences: frames plus one ground-truth box per frame.

Every loader returns a :class:`Sequence` whose ``boxes (T, 4)`` are float64 ``x, y, w, h`` in
0-based pixels (the package convention, see :mod:`torchtrack.boxes`), one row per frame, with a
row of NaN where the target is absent.

Supported layouts (:func:`load_sequence` detects them, :func:`find_sequences` walks folders):

* **OTB**: ``<seq>/img/*.jpg`` + ``groundtruth_rect.txt`` (``x,y,w,h``, 1-based; comma, tab or
  space delimited). ``groundtruth_rect.<k>.txt`` files (several targets, e.g. Jogging) give one
  sequence each, named ``<seq>-<k>``. Sequences may start at a later frame (David: 0300): line k
  belongs to the k-th frame in sorted order. UAV123-style ``NaN,NaN,NaN,NaN`` rows mean absent.
* **BoBoT**: ``<seq>/frames/*.jpg`` + ``gt.txt`` (``x1,y1,x2,y2``, 0-based corners, NaN rows =
  absent; a row with reversed corners, ``x2 < x1`` or ``y2 < y1``, is an error naming the line).
* **VOT**: ``<seq>/groundtruth.txt`` with 8-value polygons (or 4-value ``x,y,w,h``
  rectangles, 0-based) and frames in ``<seq>/color/`` or ``<seq>/`` itself; a polygon becomes
  the axis-aligned box of its min/max corners.
* **Generic CSV**: ``<seq>/{img,frames,images}/`` + ``<seq>/{groundtruth,gt,boxes}.csv``, see
  :func:`read_box_csv` for the CSV format.
* **Video + CSV**: ``clip.mp4`` beside ``clip.csv`` (same stem).

Rules applied by every loader:

* The number of ground-truth rows must equal the number of frames; otherwise a
  :class:`~torchtrack.errors.SequenceError` names the file and both counts (pass
  ``on_mismatch="truncate"`` to keep the common prefix instead).
* Blank lines at the end of a file are ignored; a blank or non-numeric line elsewhere is an
  error naming the line number.
* Rows of NaN, and rows whose width or height is not positive, mean "target absent".
* When frame files carry numbers, a gap in the numbering (a missing frame) is an error: it would
  shift every later box onto the wrong frame.
"""

from __future__ import annotations

import csv
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchtrack.errors import ConfigError, SequenceError, VideoError
from torchtrack.io.mot import MAX_SEQ_LENGTH
from torchtrack.io.text import EMPTY_FIELD, SEPARATORS, is_float_text, text_float
from torchtrack.io.video import VIDEO_EXTENSIONS, FrameSource, list_image_files, natural_key

__all__ = [
    "Sequence",
    "detect_layout",
    "find_sequences",
    "load_bobot",
    "load_frames_csv",
    "load_otb",
    "load_sequence",
    "load_video_csv",
    "load_vot",
    "parse_box_file",
    "read_box_csv",
]

_FRAME_DIRS = ("img", "frames", "images", "color")
_CSV_NAMES = ("groundtruth.csv", "gt.csv", "boxes.csv")
_MISMATCH = ("error", "truncate")


@dataclass
class Sequence:
    """A tracking sequence: frames and ground truth.

    Attributes:
        name: short name (folder name, ``Jogging-1`` style for multi-target OTB files).
        boxes: ``(T, 4)`` float64 ground truth ``x, y, w, h``, 0-based pixels; NaN rows = absent.
        frames: ``T`` image paths in order, or ``None`` for a video sequence.
        video: the video file of a video sequence, else ``None``.
        gt_path: the ground-truth file the boxes came from.
        layout: ``"otb"`` | ``"bobot"`` | ``"vot"`` | ``"csv"`` | ``"video"``.
        first_frame: the number in the first frame's file name (300 for OTB David), else 0.
    """

    name: str
    boxes: torch.Tensor
    gt_path: Path
    layout: str
    frames: list[Path] | None = None
    video: Path | None = None
    first_frame: int = 0
    root: Path | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.boxes.shape[0])

    @property
    def present(self) -> torch.Tensor:
        """``(T,)`` bool: the target is present (its box is finite)."""
        return torch.isfinite(self.boxes).all(dim=1)

    def open(self, color: str = "rgb") -> FrameSource:
        """Open the frames as a :class:`~torchtrack.io.video.FrameSource`."""
        if self.frames is not None:
            return FrameSource(self.frames, color=color)
        if self.video is None:
            raise SequenceError(f"sequence {self.name} has neither frames nor a video")
        return FrameSource(self.video, color=color)

    def head(self, n: int) -> Sequence:
        """The first ``n`` frames as a new sequence (quick runs and tests)."""
        n = max(1, min(int(n), len(self)))
        return Sequence(
            name=self.name,
            boxes=self.boxes[:n].clone(),
            gt_path=self.gt_path,
            layout=self.layout,
            frames=None if self.frames is None else self.frames[:n],
            video=self.video,
            first_frame=self.first_frame,
            root=self.root,
        )


# ---------------------------------------------------------------------------------------------
# Parsing box files
# ---------------------------------------------------------------------------------------------
def _parse_rows(path: Path, allowed: tuple[int, ...]) -> list[list[float]]:
    """Numbers of each line of a box file; NaN-only or single-value lines become ``[]``
    placeholders only when 1 is in ``allowed`` (VOT "0" = absent)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise SequenceError(f"ground-truth file {path} cannot be read: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise SequenceError(f"ground-truth file {path} is not a text file: {exc}") from exc
    lines = text.splitlines()
    while lines and not lines[-1].strip():
        lines.pop()
    if not lines:
        raise SequenceError(f"ground-truth file {path} is empty")
    rows: list[list[float]] = []
    for no, line in enumerate(lines, start=1):
        s = line.strip()
        if not s:
            raise SequenceError(f"{path} line {no} is blank (blank lines only allowed at the end)")
        if EMPTY_FIELD.search(s):  # '10,,20,30,40' was read as the box 10,20,30,40
            raise SequenceError(
                f"{path} line {no} has an empty value (a comma first, or two commas with "
                f"nothing between): {s[:60]!r}"
            )
        parts = [p for p in SEPARATORS.split(s) if p]
        try:
            vals = [text_float(p) for p in parts]
        except ValueError:
            raise SequenceError(
                f"{path} line {no} is not numeric: {s[:60]!r} (expected "
                f"{' or '.join(str(a) for a in allowed)} numbers separated by commas, tabs or "
                "spaces)"
            ) from None
        if len(vals) not in allowed:
            raise SequenceError(
                f"{path} line {no} has {len(vals)} values, expected "
                f"{' or '.join(str(a) for a in allowed)}: {s[:60]!r}"
            )
        rows.append(vals)
    return rows


def _check_corner_order(path: Path, rows: list[list[float]]) -> None:
    """A corner row whose second corner lies left of or above its first (``x2 < x1`` or
    ``y2 < y1``) is an error: its negative width read as "target absent" without a word, and
    the frame dropped out of the scores. BoBoT marks an absent target with ``NaN`` rows (kept);
    a zero-size row stays absent under the common rule.

    Raises:
        SequenceError: the file, the line and its corners.
    """
    for no, row in enumerate(rows, start=1):  # no blank lines before the last
        _check_corners(path, no, row)


def _check_corners(path: Path, no: int, row: list[float]) -> None:
    """:func:`_check_corner_order` of one row ``x1, y1, x2, y2`` at line ``no`` of ``path``."""
    x1, y1, x2, y2 = row
    if all(math.isfinite(v) for v in row) and (x2 < x1 or y2 < y1):
        axis = "x2 < x1" if x2 < x1 else "y2 < y1"
        raise SequenceError(
            f"{path} line {no}: corners x1,y1,x2,y2 = {x1:g},{y1:g},{x2:g},{y2:g} are "
            f"reversed ({axis}); the second corner must be the bottom-right one (an absent "
            "target is a NaN,NaN,NaN,NaN row)"
        )


def _absent_to_nan(boxes: torch.Tensor) -> torch.Tensor:
    """Rows with a NaN/inf value or a non-positive size become all-NaN (target absent)."""
    bad = ~torch.isfinite(boxes).all(dim=1) | (boxes[:, 2] <= 0) | (boxes[:, 3] <= 0)
    out = boxes.clone()
    out[bad] = math.nan
    return out


def parse_box_file(path: str | os.PathLike, box_format: str = "xywh", one_based: bool = False):
    """Read a text file of one box per line into ``(T, 4)`` float64 xywh 0-based boxes.

    Args:
        path: the file; values separated by commas, tabs or spaces.
        box_format: ``"xywh"`` (4 values), ``"xyxy"`` (4 values, corners) or ``"polygon"``
            (8 values x1,y1,...,x4,y4 -> axis-aligned min/max box; 4-value rows are read as xywh
            and 1-value rows ``0`` or ``NaN``, as VOT's, mean absent).
        one_based: subtract 1 from x and y (OTB files are 1-based).

    Returns:
        ``(T, 4)`` float64; NaN rows where the target is absent.

    Raises:
        SequenceError: unreadable file, non-numeric line or wrong number of values, a
            ``"polygon"`` one-value line other than 0 / NaN, or ``"xyxy"`` corners reversed
            (``x2 < x1`` or ``y2 < y1``), with the line number.
    """
    p = Path(path)
    if box_format in ("xywh", "xyxy"):
        rows = _parse_rows(p, (4,))
        t = torch.tensor(rows, dtype=torch.float64)
        if box_format == "xyxy":
            _check_corner_order(p, rows)
            t = torch.stack((t[:, 0], t[:, 1], t[:, 2] - t[:, 0], t[:, 3] - t[:, 1]), dim=1)
    elif box_format == "polygon":
        rows = _parse_rows(p, (1, 4, 8))
        out = []
        for no, r in enumerate(rows, start=1):  # no blank lines before the last
            if len(r) == 8:
                xs, ys = r[0::2], r[1::2]
                if any(math.isnan(v) for v in r):
                    out.append([math.nan] * 4)
                else:
                    out.append([min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys)])
            elif len(r) == 4:
                out.append(r)
            elif r[0] == 0 or math.isnan(r[0]):  # VOT long-term / occlusion marker
                out.append([math.nan] * 4)
            else:  # '5' (a cut line, a results file's 1 / 2 marker) was read as absent
                raise SequenceError(
                    f"{p} line {no} is the single value {r[0]:g}: a one-value line marks the "
                    "target absent with 0 or NaN (a box is 4 or 8 values)"
                )
        t = torch.tensor(out, dtype=torch.float64)
    else:
        raise ConfigError(f"box_format must be xywh, xyxy or polygon, got {box_format!r}")
    if one_based:
        t[:, :2] -= 1.0
    return _absent_to_nan(t)


_CSV_COLUMN_SETS = {
    ("x", "y", "w", "h"): "xywh",
    ("x1", "y1", "x2", "y2"): "xyxy",
}


def read_box_csv(path: str | os.PathLike, n_frames: int | None = None) -> torch.Tensor:
    """Read a CSV of boxes into ``(T, 4)`` float64 xywh 0-based boxes.

    Format: an optional header row. Without a header each row is ``x,y,w,h`` (0-based pixels)
    for consecutive frames. With a header, the columns ``x,y,w,h`` or ``x1,y1,x2,y2`` are used
    (any order, other columns ignored); a ``frame`` column gives each row's 0-based frame index
    (frames without a row are absent; ``n_frames`` sets the length); a ``visible`` column with
    value 0 marks the row absent. This reads the ``--out`` CSV written by ``torchtrack track``.

    Raises:
        SequenceError: missing columns, non-numeric values (with the line number), duplicate
            frames, ``x1,y1,x2,y2`` corners reversed (``x2 < x1`` or ``y2 < y1``).
    """
    p = Path(path)
    try:
        with open(p, newline="", encoding="utf-8-sig") as f:
            rows = [r for r in csv.reader(f)]
    except OSError as exc:
        raise SequenceError(f"box CSV {p} cannot be read: {exc}") from exc
    except UnicodeDecodeError as exc:  # was a traceback, as was csv.Error below
        raise SequenceError(f"box CSV {p} is not a text file (not UTF-8): {exc}") from None
    except csv.Error as exc:  # e.g. a field past the csv module's size limit
        raise SequenceError(f"box CSV {p} is not a CSV of boxes: {exc}") from None
    while rows and not any(c.strip() for c in rows[-1]):
        rows.pop()
    if not rows:
        raise SequenceError(f"box CSV {p} is empty")
    header = [c.strip().lower() for c in rows[0]]
    has_header = not all(is_float_text(c) for c in header if c)
    if not has_header:
        return parse_box_file(p, "xywh")
    fmt = None
    for cols, name in _CSV_COLUMN_SETS.items():
        if all(c in header for c in cols):
            fmt, idx = name, [header.index(c) for c in cols]
            break
    if fmt is None:
        raise SequenceError(
            f"box CSV {p} header {rows[0]} lacks the columns x,y,w,h or x1,y1,x2,y2"
        )
    fcol = header.index("frame") if "frame" in header else None
    vcol = header.index("visible") if "visible" in header else None
    frames: list[int] = []
    lines: dict[int, int] = {}  # frame -> the line that gave it
    vals: list[list[float]] = []
    for no, r in enumerate(rows[1:], start=2):
        if not any(c.strip() for c in r):
            raise SequenceError(f"{p} line {no} is blank (blank lines only allowed at the end)")
        try:
            v = [text_float(r[i]) for i in idx]
            if vcol is not None and text_float(r[vcol]) == 0:
                v = [math.nan] * 4
            fv = text_float(r[fcol]) if fcol is not None else 0.0
        except (ValueError, IndexError):
            raise SequenceError(f"{p} line {no} is not numeric or too short: {r}") from None
        if fmt == "xyxy":  # a reversed row read as absent, without a word
            _check_corners(p, no, v)
        if fcol is not None:
            # 1.5 was read as frame 1, inf was an OverflowError traceback
            if not fv.is_integer():
                raise SequenceError(
                    f"{p} line {no}: frame {r[fcol].strip()!r} is not a whole frame index"
                )
            f = int(fv)
            if f >= MAX_SEQ_LENGTH:  # 1e300 was a TypeError from torch.full, 1e9 a 32 GB table
                raise SequenceError(
                    f"{p} line {no}: frame {r[fcol].strip()!r} is beyond any sequence (frame "
                    f"indices are below {MAX_SEQ_LENGTH})"
                )
            if f in lines:
                raise SequenceError(
                    f"box CSV {p} lists a frame more than once: frame {f} on lines "
                    f"{lines[f]} and {no}"
                )
            lines[f] = no
            frames.append(f)
        vals.append(v)
    t = torch.tensor(vals, dtype=torch.float64).reshape(-1, 4)
    if fmt == "xyxy":
        t = torch.stack((t[:, 0], t[:, 1], t[:, 2] - t[:, 0], t[:, 3] - t[:, 1]), dim=1)
    if fcol is not None:
        if frames and min(frames) < 0:
            raise SequenceError(f"box CSV {p} has a negative frame index {min(frames)}")
        length = n_frames if n_frames is not None else (max(frames) + 1 if frames else 0)
        if frames and max(frames) >= length:
            raise SequenceError(
                f"box CSV {p} has a row for frame {max(frames)} but the sequence has "
                f"{length} frames"
            )
        full = torch.full((length, 4), math.nan, dtype=torch.float64)
        if frames:
            full[torch.tensor(frames)] = t
        t = full
    return _absent_to_nan(t)


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------
def _frame_number(p: Path) -> int | None:
    m = re.findall(r"\d+", p.stem)
    return int(m[-1]) if m else None


def _list_frames(folder: Path) -> tuple[list[Path], int]:
    """Sorted frame files of ``folder`` and the first frame's number; checks numbering gaps."""
    try:
        files = list_image_files(folder)
    except VideoError as exc:
        raise SequenceError(str(exc)) from None
    nums = [_frame_number(f) for f in files]
    if all(n is not None for n in nums):
        for prev, cur, before, f in zip(nums, nums[1:], files, files[1:], strict=False):
            if cur == prev:  # natural order keeps numbers ascending: only a repeat is left
                raise SequenceError(
                    f"frame folder {folder}: {before.name} and {f.name} both carry frame number "
                    f"{cur} (two frames for one box); keep one of them"
                )
            if cur != prev + 1:
                missing = f"{prev + 1}" if cur == prev + 2 else f"{prev + 1}..{cur - 1}"
                raise SequenceError(
                    f"frame folder {folder}: frame number(s) {missing} missing before {f.name} "
                    "(every later box would be matched to the wrong frame)"
                )
        return files, int(nums[0])
    return files, 0


def _match(
    name: str, boxes: torch.Tensor, n_frames: int, gt_path: Path, what: str, on_mismatch: str
) -> tuple[torch.Tensor, int]:
    if on_mismatch not in _MISMATCH:
        raise ConfigError(f"on_mismatch must be error or truncate, got {on_mismatch!r}")
    n_gt = int(boxes.shape[0])
    if n_gt == n_frames:
        return boxes, n_frames
    if on_mismatch == "error":
        raise SequenceError(
            f"{gt_path} has {n_gt} box rows but {what} has {n_frames} frames; they must match "
            "one to one (use on_mismatch='truncate' / --on-mismatch truncate to keep the "
            "common prefix)"
        )
    n = min(n_gt, n_frames)
    warnings.warn(
        f"sequence {name}: {gt_path} has {n_gt} rows, {what} has {n_frames} frames; "
        f"keeping the first {n}",
        stacklevel=3,
    )
    return boxes[:n], n


def _check_first_present(seq: Sequence) -> Sequence:
    if len(seq) == 0:
        raise SequenceError(f"sequence {seq.name} has no frames")
    return seq


# ---------------------------------------------------------------------------------------------
# Loaders
# ---------------------------------------------------------------------------------------------
def _frames_sequence(
    name: str,
    folder: Path,
    boxes: torch.Tensor,
    gt: Path,
    layout: str,
    on_mismatch: str,
    root: Path,
) -> Sequence:
    files, first = _list_frames(folder)
    boxes, n = _match(name, boxes, len(files), gt, f"frame folder {folder}", on_mismatch)
    return _check_first_present(
        Sequence(
            name=name,
            boxes=boxes,
            gt_path=gt,
            layout=layout,
            frames=files[:n],
            first_frame=first,
            root=root,
        )
    )


def _otb_gt_files(folder: Path) -> list[Path]:
    return sorted(
        (p for p in folder.glob("groundtruth_rect*.txt") if p.is_file()),
        key=lambda p: natural_key(p.name),
    )


def load_otb(
    folder: str | os.PathLike, gt_file: str | None = None, *, on_mismatch: str = "error"
) -> list[Sequence]:
    """Load an OTB sequence folder (``img/`` + ``groundtruth_rect*.txt``).

    Returns one :class:`Sequence` per ground-truth file (``Jogging-1``, ``Jogging-2`` for
    ``groundtruth_rect.1.txt`` / ``.2.txt``; the folder name for a single file).

    Raises:
        SequenceError: missing ``img/`` or ground truth, bad lines, count mismatch, missing frames.
    """
    d = Path(folder)
    gts = [d / gt_file] if gt_file else _otb_gt_files(d)
    if not gts:
        raise SequenceError(f"OTB folder {d} has no groundtruth_rect*.txt")
    out = []
    for gt in gts:
        m = re.fullmatch(r"groundtruth_rect\.(\w+)\.txt", gt.name)
        name = f"{d.name}-{m.group(1)}" if m and len(gts) > 1 else d.name
        boxes = parse_box_file(gt, "xywh", one_based=True)
        out.append(_frames_sequence(name, d / "img", boxes, gt, "otb", on_mismatch, d))
    return out


def load_bobot(folder: str | os.PathLike, *, on_mismatch: str = "error") -> Sequence:
    """Load a BoBoT sequence: ``frames/`` + ``gt.txt`` with ``x1,y1,x2,y2`` rows (NaN = absent).

    Line k belongs to the k-th frame in sorted order (frames start at ``img0002``).
    """
    d = Path(folder)
    gt = d / "gt.txt"
    if not gt.is_file():
        raise SequenceError(f"BoBoT folder {d} has no gt.txt")
    boxes = parse_box_file(gt, "xyxy")
    return _frames_sequence(d.name, d / "frames", boxes, gt, "bobot", on_mismatch, d)


def load_vot(folder: str | os.PathLike, *, on_mismatch: str = "error") -> Sequence:
    """Load a VOT sequence: ``groundtruth.txt`` (8-value polygons or 4-value rectangles) and
    frames in ``color/`` or the folder itself; polygons become their axis-aligned min/max box."""
    d = Path(folder)
    gt = d / "groundtruth.txt"
    if not gt.is_file():
        raise SequenceError(f"VOT folder {d} has no groundtruth.txt")
    boxes = parse_box_file(gt, "polygon")
    frames_dir = d / "color" if (d / "color").is_dir() else d
    return _frames_sequence(d.name, frames_dir, boxes, gt, "vot", on_mismatch, d)


def load_frames_csv(
    frames: str | os.PathLike,
    csv_path: str | os.PathLike,
    *,
    name: str | None = None,
    on_mismatch: str = "error",
) -> Sequence:
    """A folder of frames plus a CSV of boxes (format: :func:`read_box_csv`)."""
    fd, cp = Path(frames), Path(csv_path)
    files, _ = _list_frames(fd)
    boxes = read_box_csv(cp, n_frames=len(files))
    return _frames_sequence(name or fd.parent.name, fd, boxes, cp, "csv", on_mismatch, fd.parent)


def load_video_csv(
    video: str | os.PathLike,
    csv_path: str | os.PathLike | None = None,
    *,
    name: str | None = None,
    on_mismatch: str = "error",
) -> Sequence:
    """A video file plus a CSV of boxes (default: same stem, ``.csv``). The frame count comes
    from the video header; a video that ends early is reported when it is read."""
    v = Path(video)
    cp = Path(csv_path) if csv_path is not None else v.with_suffix(".csv")
    if not cp.is_file():
        raise SequenceError(f"video {v} has no box CSV {cp}")
    try:
        src = FrameSource(v)
    except VideoError as exc:
        raise SequenceError(str(exc)) from None
    n = len(src)
    src.close()
    boxes = read_box_csv(cp, n_frames=n if n > 0 else None)
    if n > 0:
        boxes, _ = _match(name or v.stem, boxes, n, cp, f"video {v}", on_mismatch)
    return _check_first_present(
        Sequence(
            name=name or v.stem, boxes=boxes, gt_path=cp, layout="video", video=v, root=v.parent
        )
    )


def detect_layout(path: str | os.PathLike) -> str | None:
    """The layout of a sequence folder or video file, or ``None`` if it is not a sequence."""
    p = Path(path)
    if p.is_file():
        return (
            "video"
            if p.suffix.lower() in VIDEO_EXTENSIONS and p.with_suffix(".csv").is_file()
            else None
        )
    if not p.is_dir():
        return None
    if _otb_gt_files(p) and (p / "img").is_dir():
        return "otb"
    if (p / "gt.txt").is_file() and (p / "frames").is_dir():
        return "bobot"
    if (p / "groundtruth.txt").is_file():
        return "vot"
    if any((p / c).is_file() for c in _CSV_NAMES) and any((p / f).is_dir() for f in _FRAME_DIRS):
        return "csv"
    return None


def load_sequence(path: str | os.PathLike, *, on_mismatch: str = "error") -> list[Sequence]:
    """Load the sequence(s) at ``path`` (a sequence folder or a video with a same-stem CSV),
    detecting the layout. Returns a list (an OTB folder may hold several targets).

    Raises:
        SequenceError: ``path`` is not a recognised sequence, or it is malformed.
    """
    p = Path(path)
    layout = detect_layout(p)
    if layout == "otb":
        return load_otb(p, on_mismatch=on_mismatch)
    if layout == "bobot":
        return [load_bobot(p, on_mismatch=on_mismatch)]
    if layout == "vot":
        return [load_vot(p, on_mismatch=on_mismatch)]
    if layout == "csv":
        csv_path = next(p / c for c in _CSV_NAMES if (p / c).is_file())
        frames = next(p / f for f in _FRAME_DIRS if (p / f).is_dir())
        return [load_frames_csv(frames, csv_path, name=p.name, on_mismatch=on_mismatch)]
    if layout == "video":
        return [load_video_csv(p, on_mismatch=on_mismatch)]
    raise SequenceError(
        f"{p} is not a tracking sequence: expected img/ + groundtruth_rect.txt (OTB), frames/ + "
        "gt.txt (BoBoT), groundtruth.txt (VOT), a frames folder + groundtruth.csv, or a video "
        "with a same-stem .csv"
    )


def find_sequences(
    path: str | os.PathLike, *, max_depth: int = 3, on_mismatch: str = "error"
) -> list[Sequence]:
    """All sequences at or below ``path`` (a sequence, or a folder of sequences, nested up to
    ``max_depth`` levels), in natural name order.

    Raises:
        SequenceError: ``path`` does not exist or holds no sequence; a malformed sequence
            raises too (it is named in the message) rather than being silently skipped.
    """
    root = Path(path)
    if not root.exists():
        raise SequenceError(f"sequence path {root} does not exist")
    found: list[Sequence] = []

    def walk(p: Path, depth: int) -> None:
        if detect_layout(p) is not None:
            found.extend(load_sequence(p, on_mismatch=on_mismatch))
            return
        if depth >= max_depth or not p.is_dir():
            return
        for child in sorted(p.iterdir(), key=lambda c: natural_key(c.name)):
            if child.name.startswith("."):
                continue
            if child.is_dir() or child.suffix.lower() in VIDEO_EXTENSIONS:
                walk(child, depth + 1)

    walk(root, 0)
    if not found:
        raise SequenceError(
            f"no tracking sequence found in {root} (searched {max_depth} levels deep)"
        )
    return found
