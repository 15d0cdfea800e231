"""Frame sources: a video file, a folder of images, or a camera index.

Every source yields frames as ``torch.uint8`` tensors of shape ``(C, H, W)`` in **RGB** order.
Colour handling is chosen once with ``color``:

* ``"rgb"`` (default): every frame has ``C = 3``; grayscale images are expanded to three equal
  channels, so colour models and OpenCV peers run unchanged on grayscale sequences.
* ``"keep"``: grayscale images keep ``C = 1``, colour ones ``C = 3`` (video files and cameras are
  always decoded as colour by OpenCV, so they give ``C = 3``).
* ``"gray"``: every frame is converted to ``C = 1`` (ITU-R BT.601 luma, as ``cv2.cvtColor``).

Unreadable frames do not stop iteration: :meth:`FrameSource.items` yields ``(index, None)`` for
them, plain iteration skips them, and both record them in :attr:`FrameSource.bad_frames`.
A source that cannot be opened at all (missing file, empty folder, absent camera) raises
:class:`~torchtrack.errors.VideoError`.

**One image decoder.** Every image file torchtrack reads (frames here, training and
calibration crops in :mod:`torchtrack.io.crops`) goes through :func:`decode_image`: the bytes
are read once, a JPEG that lacks its end-of-image marker after its last scan is reported as
truncated (libjpeg would fill the missing part with grey and only print a warning), and
``cv2.imdecode`` decodes the rest. What the native decoders print (libjpeg, libpng, FFmpeg)
is captured instead of reaching the terminal, and becomes part of the error message when the
file cannot be used.

Example::

    with open_source("clip.mp4") as src:
        for frame in src:          # (3, H, W) uint8 RGB
            ...
        print(src.n_bad, "unreadable frames")
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.errors import ConfigError, DataError, VideoError

__all__ = [
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "BadFrame",
    "FrameSource",
    "decode_image",
    "is_broken_link",
    "jpeg_is_truncated",
    "list_image_files",
    "native_output",
    "natural_key",
    "open_source",
    "read_image",
    "to_numpy_bgr",
]

IMAGE_EXTENSIONS = frozenset(
    {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".pbm", ".webp"}
)
VIDEO_EXTENSIONS = frozenset({".avi", ".mp4", ".mov", ".mkv", ".mpg", ".mpeg", ".m4v", ".wmv"})
_COLORS = ("rgb", "keep", "gray")


def natural_key(name: str) -> tuple:
    """Sort key that orders embedded numbers numerically (``img2`` before ``img10``)."""
    return tuple(int(p) if p.isdigit() else p.lower() for p in re.split(r"(\d+)", name))


def is_broken_link(p: Path) -> bool:
    """Whether ``p`` is a symbolic link whose target does not exist."""
    return p.is_symlink() and not p.exists()


def list_image_files(folder: str | os.PathLike) -> list[Path]:
    """Image files directly inside ``folder``, in natural order. Hidden files are ignored;
    broken symbolic links are listed (reading one fails, as for any unreadable frame).

    Raises:
        VideoError: the folder does not exist or holds no image file (the message points to
            ``img1/`` where the folder is a MOTChallenge sequence's).
    """
    d = Path(folder)
    if not d.is_dir():
        raise VideoError(f"frame folder {d} does not exist or is not a folder")
    # a broken symbolic link is kept: it is read (and reported) as an unreadable frame in its
    # place, where dropping it silently gave every later frame the number of the one before
    files = [
        p
        for p in d.iterdir()
        if p.suffix.lower() in IMAGE_EXTENSIONS
        and not p.name.startswith(".")
        and (p.is_file() or is_broken_link(p))
    ]
    if not files:
        hint = ""
        if (d / "img1").is_dir():  # MOTChallenge: seqinfo.ini, gt/, det/ beside img1/
            hint = f"; it looks like a MOTChallenge sequence: give its img1/ folder, {d / 'img1'}"
        raise VideoError(
            f"frame folder {d} holds no image file (looked for "
            f"{', '.join(sorted(IMAGE_EXTENSIONS))}){hint}"
        )
    return sorted(files, key=lambda p: natural_key(p.name))


def _camera_index(source) -> bool:
    """Whether a string source names a camera: ASCII digits (``int`` refuses some other
    Unicode digits, ``'²'``) and no file or folder of that name (a frame folder ``2024``)."""
    return (
        isinstance(source, str)
        and source.isascii()
        and source.isdigit()
        and not os.path.exists(source)
    )


def _check_color(color: str) -> None:
    if color not in _COLORS:
        raise ConfigError(f"color must be one of {', '.join(_COLORS)}, got {color!r}")


def _array_to_tensor(img: np.ndarray, color: str, *, bgr: bool = True) -> torch.Tensor:
    """OpenCV image ``(H, W)`` or ``(H, W, C)`` -> ``(C, H, W)`` uint8 RGB tensor."""
    if img.dtype == np.uint16:
        # 16-bit images: keep the top 8 bits (rounded), the usual display mapping.
        img = np.clip((img.astype(np.float32) / 257.0).round(), 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise DataError(f"unsupported image dtype {img.dtype}; expected 8- or 16-bit images")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 2:
        if color == "rgb":
            img = np.repeat(img[:, :, None], 3, axis=2)
        else:
            img = img[:, :, None]
    else:
        if color == "gray":
            code = cv2.COLOR_BGR2GRAY if bgr else cv2.COLOR_RGB2GRAY
            img = cv2.cvtColor(np.ascontiguousarray(img), code)[:, :, None]
        elif bgr:
            img = img[:, :, ::-1]
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))


class _NativeOutput:
    """Text the native libraries wrote to stderr while captured (see :func:`native_output`)."""

    text = ""

    def first_line(self) -> str:
        lines = [ln.strip() for ln in self.text.splitlines() if ln.strip()]
        return lines[0] if lines else ""


_capture_lock = threading.RLock()
_capture_file = None


@contextlib.contextmanager
def native_output() -> Iterator[_NativeOutput]:
    """Capture what native code (OpenCV, libjpeg, libpng, FFmpeg) writes to the process's
    stderr (file descriptor 2) inside the block; the text is in the yielded object's ``text``
    afterwards. Python-level output is flushed first and not captured. Where file descriptor 2
    cannot be redirected, nothing is captured."""
    global _capture_file
    import sys

    out = _NativeOutput()
    with _capture_lock:
        try:
            sys.stderr.flush()
        except (AttributeError, ValueError, OSError):
            pass
        try:
            if _capture_file is None:
                import atexit

                _capture_file = tempfile.TemporaryFile()
                atexit.register(_capture_file.close)
            fd = _capture_file.fileno()
            saved = os.dup(2)
        except OSError:
            yield out
            return
        try:
            os.dup2(fd, 2)
            try:
                yield out
            finally:
                os.dup2(saved, 2)
        finally:
            os.close(saved)
            size = os.lseek(fd, 0, os.SEEK_END)
            if size:
                os.lseek(fd, 0, os.SEEK_SET)
                out.text = os.read(fd, min(size, 65536)).decode("utf-8", "replace")
                os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)


def jpeg_is_truncated(data: bytes) -> bool:
    """Whether ``data`` is a JPEG cut short: it starts with the JPEG signature but has no
    end-of-image marker (``FF D9``) after its last start-of-scan (``FF DA``). In entropy-coded
    data a ``FF`` byte is always followed by ``00`` or a restart marker, so the end marker
    cannot appear inside a scan."""
    if data[:3] != b"\xff\xd8\xff":
        return False
    sos = data.rfind(b"\xff\xda")
    return sos < 0 or data.find(b"\xff\xd9", sos + 2) < 0


def decode_image(path: str | os.PathLike, flags: int = cv2.IMREAD_UNCHANGED) -> np.ndarray:
    """The one image decoder (see the module doc): ``path`` -> the OpenCV array of
    ``cv2.imdecode(..., flags)`` (BGR order, ``(H, W)`` or ``(H, W, C)``).

    Raises:
        DataError: the file is missing, not a file, empty, a truncated JPEG, or cannot be
            decoded (the message names the file and gives the decoder's own complaint).
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        if is_broken_link(p):
            raise DataError(
                f"image {p} is a broken symbolic link (to {os.readlink(p)}, which does not exist)"
            ) from None
        raise DataError(f"image {p} does not exist") from None
    except IsADirectoryError:
        raise DataError(f"image {p} is a folder, not an image file") from None
    except OSError as exc:
        raise DataError(f"image {p} cannot be read: {exc.strerror or exc}") from None
    if not data:
        raise DataError(f"image {p} is empty (0 bytes)")
    if jpeg_is_truncated(data):
        raise DataError(
            f"image {p} is truncated: a JPEG of {len(data):,} bytes without its end-of-image "
            "marker (the decoder would fill the missing part with grey)"
        )
    with native_output() as log:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if img is None or img.size == 0:
        detail = log.first_line()
        raise DataError(
            f"image {p} cannot be decoded as an image" + (f" ({detail})" if detail else "")
        )
    return img


def read_image(path: str | os.PathLike, color: str = "rgb") -> torch.Tensor:
    """Read one image file as a ``(C, H, W)`` uint8 RGB tensor (see the module doc for ``color``).

    Raises:
        DataError: the file is missing, empty, truncated or cannot be decoded.
    """
    _check_color(color)
    return _array_to_tensor(decode_image(path), color)


def to_numpy_bgr(frame: torch.Tensor) -> np.ndarray:
    """``(C, H, W)`` uint8 RGB (or ``C = 1`` gray) tensor -> ``(H, W, 3)`` contiguous BGR array,
    the layout OpenCV functions expect."""
    arr = frame.detach().cpu().numpy()
    if arr.shape[0] == 1:
        return np.ascontiguousarray(np.repeat(arr[0][:, :, None], 3, axis=2))
    return np.ascontiguousarray(arr[::-1].transpose(1, 2, 0))


@dataclass(frozen=True)
class BadFrame:
    """An unreadable frame: its 0-based index in the source and why it failed."""

    index: int
    reason: str


class FrameSource:
    """Frames of a video file, an image folder, an explicit list of image files or a camera.

    Args:
        source: a path to a video file or a folder of images, a list of image paths, or a camera
            index (``int``, or a string of ASCII digits that names no file or folder).
        color: ``"rgb"`` | ``"keep"`` | ``"gray"``, see the module doc.

    Attributes:
        kind: ``"video"`` | ``"folder"`` | ``"files"`` | ``"camera"``.
        bad_frames: the unreadable frames met so far (list of :class:`BadFrame`).
        ended_early: ``True`` when a video stopped before the frame count its header announced.

    Raises:
        VideoError: the source cannot be opened, or is none of the above (a bool, ``None``,
            a float, bytes).
    """

    def __init__(
        self, source: str | os.PathLike | int | list[str | os.PathLike], color: str = "rgb"
    ) -> None:
        _check_color(color)
        self.color = color
        self.bad_frames: list[BadFrame] = []
        self.ended_early = False
        self._cap: cv2.VideoCapture | None = None
        self._files: list[Path] | None = None
        if isinstance(source, bool):  # an int to Python: True opened camera 1
            raise VideoError(f"a bool is not a camera index, got {source!r}")
        if not isinstance(source, (str, os.PathLike, int, list, tuple)):
            raise VideoError(  # None, a float or bytes: a bare TypeError from pathlib
                "source must be a path (a video file or a frame folder), a list of image paths "
                f"or a camera index, got {type(source).__name__} {source!r}"
            )
        if isinstance(source, (list, tuple)):
            if not source:
                raise VideoError("the list of frame files is empty")
            self.kind = "files"
            self._files = [Path(p) for p in source]
            self.name = str(self._files[0].parent)
        elif isinstance(source, int) or _camera_index(source):
            index = int(source)
            self.kind = "camera"
            self.name = f"camera {index}"
            # OpenCV takes a C int (cv2.error beyond); its V4L backend dies of a segmentation
            # fault on -1 and -2 where no camera is found, taking the process with it
            if not 0 <= index < 2**31:
                raise VideoError(
                    f"camera index {source} is out of range (cameras are 0, 1, ..., at most "
                    f"{2**31 - 1})"
                )
            self._cap = cv2.VideoCapture(index)
            if not self._cap.isOpened():
                raise VideoError(f"camera index {index} cannot be opened")
        else:
            p = Path(source)
            self.name = str(p)
            if p.is_dir():
                self.kind = "folder"
                self._files = list_image_files(p)
            elif p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS:
                # one image: through the one image decoder, as in a folder. OpenCV's video
                # reader took a truncated JPEG filled with grey, and a float TIFF as black
                self.kind = "files"
                self._files = [p]
            elif p.is_file():
                self.kind = "video"
                with native_output() as log:
                    self._cap = cv2.VideoCapture(str(p))
                    opened = self._cap.isOpened()
                if not opened:
                    detail = log.first_line()
                    raise VideoError(
                        f"video file {p} cannot be opened (unknown or broken format"
                        + (f": {detail})" if detail else ")")
                    )
            elif p.exists():  # a device, a pipe or a socket: nothing to read frames from
                raise VideoError(f"video source {p} is neither a video file nor a folder of frames")
            else:
                raise VideoError(f"video source {p} does not exist")

    # -- information ---------------------------------------------------------------------------
    def __len__(self) -> int:
        """Number of frames: exact for folders, the header's count for videos, 0 for cameras."""
        if self._files is not None:
            return len(self._files)
        if self.kind == "video" and self._cap is not None:
            return max(int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
        return 0

    @property
    def fps(self) -> float | None:
        """Frame rate announced by a video or camera; ``None`` for image folders."""
        if self._cap is None:
            return None
        f = float(self._cap.get(cv2.CAP_PROP_FPS))
        return f if f > 0 else None

    @property
    def files(self) -> list[Path] | None:
        """The image files of a folder or file-list source, else ``None``."""
        return None if self._files is None else list(self._files)

    @property
    def n_bad(self) -> int:
        """Number of unreadable frames met so far."""
        return len(self.bad_frames)

    # -- iteration -----------------------------------------------------------------------------
    def items(self) -> Iterator[tuple[int, torch.Tensor | None]]:
        """Yield ``(index, frame)`` for every frame; ``frame`` is ``None`` when unreadable.

        ``frame`` is ``(C, H, W)`` uint8 RGB. Indices are 0-based positions in the source.
        """
        if self._files is not None:
            for i, path in enumerate(self._files):
                try:
                    yield i, read_image(path, self.color)
                except DataError as exc:
                    self.bad_frames.append(BadFrame(i, str(exc)))
                    yield i, None
            return
        if self._cap is None:
            raise VideoError(f"{self.name} is closed")
        expected = len(self) if self.kind == "video" else 0
        i = 0
        while True:
            with native_output():
                ok, img = self._cap.read()
            if not ok or img is None:
                if expected and i < expected:
                    # OpenCV cannot tell a corrupt frame from the end of the stream.
                    self.ended_early = True
                    self.bad_frames.append(
                        BadFrame(i, f"video ended at frame {i} of {expected} announced")
                    )
                return
            yield i, _array_to_tensor(img, self.color)
            i += 1

    def __iter__(self) -> Iterator[torch.Tensor]:
        """Yield the readable frames ``(C, H, W)`` uint8 RGB, skipping (and recording) bad ones."""
        for _, frame in self.items():
            if frame is not None:
                yield frame

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __enter__(self) -> FrameSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"FrameSource({self.name!r}, kind={self.kind!r}, color={self.color!r})"


def open_source(
    source: str | os.PathLike | int | list[str | os.PathLike], color: str = "rgb"
) -> FrameSource:
    """Open a video file, image folder, list of image files or camera index as a
    :class:`FrameSource` (see the class for arguments and errors)."""
    return FrameSource(source, color=color)
