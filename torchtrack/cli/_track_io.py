"""What ``torchtrack track`` writes: box CSVs, MOTChallenge files, annotated videos.

Every output is produced safely: rows stream into ``PATH.part`` (flushed as they come, so a
crash or Ctrl-C keeps the rows so far) and :meth:`RowWriter.close` fsyncs and renames it to
``PATH``; the video goes to a temporary file in the same folder, renamed at the end. Nothing is
created before the first tracked frame, and :meth:`RowWriter.discard` removes what a run that
tracked nothing began, so a failed run leaves no file that looks like a result.
"""

from __future__ import annotations

import colorsys
import contextlib
import itertools
import os
from collections import deque

__all__ = [
    "BoxWriter",
    "MotStreamWriter",
    "MultiCsvWriter",
    "RowWriter",
    "Trails",
    "VideoOut",
    "draw",
    "draw_multi",
    "identity_colour",
]


class RowWriter:
    """Text rows streamed into ``PATH.part``, renamed to ``PATH`` by :meth:`close`.

    The file is opened on the first :meth:`write` (with ``header`` first, when given).
    """

    def __init__(self, path: str, header: str | None = None) -> None:
        self.path = os.fspath(path)
        self.part = self.path + ".part"
        self.header = header
        self._f = None
        self.rows = 0

    def write(self, text: str) -> None:
        if self._f is None:
            try:
                self._f = open(self.part, "w", encoding="utf-8", newline="")
            except OSError as exc:  # checked before the run; the folder changed since
                from torchtrack.io.atomic import write_error

                raise write_error(self.path, exc) from None
            if self.header is not None:
                self._f.write(self.header + "\n")
        if text:
            self._f.write(text)
            self.rows += text.count("\n")
        self._f.flush()

    def close(self) -> None:
        """Finish: fsync and rename ``PATH.part`` to ``PATH`` (a header-only or empty file
        when nothing was written: the run found nothing)."""
        if self._f is None:
            self.write("")
        if self._f.closed:
            return
        self._f.flush()
        os.fsync(self._f.fileno())
        self._f.close()
        from torchtrack.io.atomic import check_regular_destination

        try:  # checked before the run; something may have taken its place since
            check_regular_destination(self.path)
        except Exception:
            self.discard()
            raise
        os.replace(self.part, self.path)

    def discard(self) -> None:
        """Remove the partial file (a run that tracked nothing)."""
        if self._f is not None and not self._f.closed:
            self._f.close()
        with contextlib.suppress(FileNotFoundError):
            os.remove(self.part)


class BoxWriter(RowWriter):
    """Single-target CSV ``frame,x,y,w,h,confidence,visible`` (a ``target`` column after
    ``frame`` when several targets are followed), one row per frame and target."""

    def __init__(self, path: str) -> None:
        super().__init__(path)
        self._multi: bool | None = None

    def _lead(self, i: int, t: int) -> str:
        return f"{i},{t}," if self._multi else f"{i},"

    def _set_header(self, b: int) -> None:
        if self._multi is None:
            self._multi = b > 1
            self.header = ("frame,target," if self._multi else "frame,") + (
                "x,y,w,h,confidence,visible"
            )

    def write_state(self, i: int, state) -> None:
        box = state.box.tolist()
        self._set_header(len(box))
        lines = []
        for t, (b, c, v) in enumerate(
            zip(box, state.confidence.tolist(), state.visible.tolist(), strict=True)
        ):
            lines.append(
                self._lead(i, t)
                + ",".join(f"{x:.2f}" for x in b)
                + f",{float(c):.4f},{int(bool(v))}\n"
            )
        self.write("".join(lines))

    def write_bad(self, i: int, last) -> None:
        """Row(s) for an unreadable frame after the first tracked one: the previous box,
        confidence 0, not visible."""
        import dataclasses

        import torch

        self.write_state(
            i,
            dataclasses.replace(
                last,
                confidence=torch.zeros_like(last.confidence),
                visible=torch.zeros_like(last.visible),
            ),
        )


class MultiCsvWriter(RowWriter):
    """Multi-target CSV ``frame,target,x,y,w,h,confidence,detected``: one row per reported
    target and frame (``frame`` 0-based, ``target`` the identity)."""

    HEADER = "frame,target,x,y,w,h,confidence,detected"

    def __init__(self, path: str) -> None:
        super().__init__(path, header=self.HEADER)

    def write_targets(self, i: int, out) -> None:
        lines = [
            f"{i},{k}," + ",".join(f"{x:.2f}" for x in b) + f",{float(c):.4f},{int(bool(d))}\n"
            for k, b, c, d in zip(
                out.ids.tolist(),
                out.boxes.tolist(),
                out.confidence.tolist(),
                out.detected.tolist(),
                strict=True,
            )
        ]
        self.write("".join(lines))


class MotStreamWriter(RowWriter):
    """MOTChallenge results streamed row by row: ``frame,id,x,y,w,h,conf,-1,-1,-1`` with
    1-based frames and pixels (the format of :func:`torchtrack.io.mot.write_mot`)."""

    def write_targets(self, i: int, out) -> None:
        from torchtrack.io.mot import format_mot_row

        lines = [
            format_mot_row(i, k, b, c)
            for k, b, c in zip(
                out.ids.tolist(), out.boxes.tolist(), out.confidence.tolist(), strict=True
            )
        ]
        self.write("".join(lines))


class VideoOut:
    """An annotated video written to a temporary file next to ``path`` and renamed on
    :meth:`close` (``.avi``: MJPG, anything else: mp4v); opened on the first frame."""

    def __init__(self, path: str, fps: float | None) -> None:
        self.path = os.fspath(path)
        self.fps = float(fps or 25.0)
        self._writer = None
        self._stack = contextlib.ExitStack()
        self._tmp = None
        self._last = None

    def repeat(self) -> None:
        """Write the last frame again (for a source frame that could not be read: the video
        keeps the source's timing); nothing before the first frame."""
        if self._last is not None:
            self._writer.write(self._last)

    def write(self, img) -> None:
        import cv2

        from torchtrack.errors import VideoError
        from torchtrack.io.atomic import atomic_path

        if self._writer is None:
            from torchtrack.io.video import native_output

            self._tmp = self._stack.enter_context(atomic_path(self.path))
            h, w = img.shape[:2]
            ext = os.path.splitext(self.path)[1].lower()
            fourcc = cv2.VideoWriter_fourcc(*("MJPG" if ext == ".avi" else "mp4v"))
            with native_output() as log:  # OpenCV's own log lines, kept out of the terminal
                self._writer = cv2.VideoWriter(str(self._tmp), fourcc, self.fps, (w, h))
                opened = self._writer.isOpened()
            if not opened:
                self.discard()
                detail = log.first_line()
                raise VideoError(
                    f"cannot write video {self.path!r} (use .mp4 or .avi)"
                    + (f": {detail}" if detail else "")
                )
        self._writer.write(img)
        self._last = img

    def close(self) -> None:
        """Finish and rename into place (nothing when no frame was written)."""
        if self._writer is not None:
            self._writer.release()
            self._writer = None
            self._stack.close()

    def discard(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
        if self._tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.remove(self._tmp)
        self._stack.pop_all()


#: BGR colours: a visible target, a lost one, particles.
_GREEN, _RED, _PARTICLE = (60, 220, 60), (40, 40, 230), (230, 200, 40)


def draw(frame, state, tracker=None, max_particles: int = 200):
    """An annotated BGR image ``(H, W, 3)`` of ``frame (C, H, W)``: each target's box (green
    when visible, red when lost) with its confidence, and, given a ``tracker`` with
    ``particle_boxes()``, the centres of up to ``max_particles`` particles per target."""
    import cv2

    from torchtrack.io.video import to_numpy_bgr

    img = to_numpy_bgr(frame).copy()
    if tracker is not None and hasattr(tracker, "particle_boxes"):
        _draw_particles(img, tracker.particle_boxes(), max_particles, lambda _: _PARTICLE)
    for b, c, v in zip(
        state.box.tolist(), state.confidence.tolist(), state.visible.tolist(), strict=True
    ):
        if any(t != t for t in b):  # NaN box: nothing to draw
            continue
        x, y, w, h = (round(t) for t in b)
        col = _GREEN if v else _RED
        cv2.rectangle(img, (x, y), (x + w, y + h), col, 2, lineType=cv2.LINE_AA)
        label = f"{float(c):.2f}" + ("" if v else " lost")
        cv2.putText(
            img, label, (x, max(12, y - 4)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, col, 1, cv2.LINE_AA
        )
    return img


def _draw_particles(img, pb, max_particles: int, colour) -> None:
    import cv2

    step = max(1, pb.shape[1] // max_particles)
    centres = (pb[:, ::step, :2] + pb[:, ::step, 2:] / 2).round().long().tolist()
    for r, row in enumerate(centres):
        col = colour(r)
        for cx, cy in row:
            cv2.circle(img, (cx, cy), 1, col, -1, lineType=cv2.LINE_AA)


def identity_colour(k: int) -> tuple[int, int, int]:
    """A bright BGR colour for identity ``k``, well apart from its neighbours (golden-ratio
    hue steps)."""
    h = (k * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(h, 0.85, 1.0)
    return (round(255 * b), round(255 * g), round(255 * r))


class Trails:
    """The last ``length`` centres of every identity; identities not seen for ``forget``
    frames are dropped (memory stays flat on long videos)."""

    def __init__(self, length: int = 20, forget: int = 50) -> None:
        self.length, self.forget = length, forget
        self._pts: dict[int, deque] = {}
        self._seen: dict[int, int] = {}

    def add(self, i: int, out) -> None:
        for k, b in zip(out.ids.tolist(), out.boxes.tolist(), strict=True):
            q = self._pts.setdefault(k, deque(maxlen=self.length))
            q.append((round(b[0] + b[2] / 2), round(b[1] + b[3])))  # bottom centre: the feet
            self._seen[k] = i
        for k in [k for k, last in self._seen.items() if i - last > self.forget]:
            del self._pts[k], self._seen[k]

    def items(self):
        return self._pts.items()


def draw_multi(frame, out, trails: Trails | None = None, particles=None, max_particles: int = 60):
    """An annotated BGR image of ``frame (C, H, W)``: each reported target's box and identity
    in its own colour (a thin box when it coasts without a detection), its trail, and, given
    ``particles (T, N, 4)``, particle centres."""
    import cv2

    from torchtrack.io.video import to_numpy_bgr

    img = to_numpy_bgr(frame).copy()
    if particles is not None and particles.shape[0]:
        _draw_particles(img, particles, max_particles, lambda _: _PARTICLE)
    if trails is not None:
        for k, pts in trails.items():
            col = identity_colour(k)
            for a, b in itertools.pairwise(pts):
                cv2.line(img, a, b, col, 2, lineType=cv2.LINE_AA)
    for k, b, d in zip(out.ids.tolist(), out.boxes.tolist(), out.detected.tolist(), strict=True):
        x, y, w, h = (round(t) for t in b)
        col = identity_colour(k)
        cv2.rectangle(img, (x, y), (x + w, y + h), col, 2 if d else 1, lineType=cv2.LINE_AA)
        label = str(k)
        (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
        ty = max(th + base, y)
        cv2.rectangle(img, (x, ty - th - base), (x + tw + 2, ty), col, -1)
        cv2.putText(
            img, label, (x + 1, ty - base), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1,
            cv2.LINE_AA,
        )  # fmt: skip
    return img
