"""Typed exceptions. Every error a user can cause is one of these, with a message that says
what was expected, what came, and which file or argument it concerns."""

from __future__ import annotations

import numbers


class TorchTrackError(Exception):
    """Base class of every error raised on purpose by torchtrack."""


class ShapeError(TorchTrackError, ValueError):
    """A tensor or array has the wrong shape, dtype or number of channels."""


class BoxError(TorchTrackError, ValueError):
    """A box has zero or negative size, is not finite, or lies outside the frame."""


class ConfigError(TorchTrackError, ValueError):
    """A configuration value or key is invalid, unknown or missing."""


class DataError(TorchTrackError, ValueError):
    """Input data is unusable: an empty folder, an unreadable image, NaN scores, bad labels."""


class ModelFormatError(TorchTrackError, ValueError):
    """A model file is truncated, edited, of an unknown format version or otherwise invalid."""


class VideoError(TorchTrackError, OSError):
    """A video, camera or frame folder cannot be opened or read."""


class SequenceError(TorchTrackError, ValueError):
    """A tracking sequence (frames + ground truth) is malformed."""


class MotFormatError(SequenceError):
    """A MOTChallenge file (ground truth, detections, results) or ``seqinfo.ini`` is malformed or
    does not fit its sequence; the message names the file and the line."""


class MissingDependencyError(TorchTrackError, ImportError):
    """An optional dependency is not installed; the message gives the command that installs it."""


class NotFittedError(TorchTrackError, RuntimeError):
    """An estimator was used before ``fit``."""


class FilterError(TorchTrackError, RuntimeError):
    """A particle-filter step received an invalid likelihood (e.g. NaN)."""


class TrackerError(TorchTrackError, RuntimeError):
    """A tracker was used wrongly (e.g. ``update`` before ``init``) or failed."""


class TrainingWarning(UserWarning):
    """Training finished but did not reach what was asked (e.g. a false-positive rate)."""


class BackendError(TorchTrackError, RuntimeError):
    """A distributed backend cannot be used: Ray is not installed, its cluster cannot be reached,
    or it refused the connection."""


def is_integer(x: object) -> bool:
    """An integer setting: Python's or numpy's, not a bool (int() took 2.5 as 2 and True as
    1). The test every bad-input check of a whole-number setting starts from."""
    return not isinstance(x, bool) and isinstance(x, numbers.Integral)


def is_number(x: object) -> bool:
    """A real-number setting: Python's or numpy's, not a bool nor a string (NaN and inf
    included: check finiteness where it matters)."""
    return not isinstance(x, bool) and isinstance(x, numbers.Real)
