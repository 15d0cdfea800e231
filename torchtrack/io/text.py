"""Numbers in text files (box files, MOT rows, score CSVs, command-line values), read as those
files mean them: Python's ``float()`` / ``int()`` less their own syntax of underscores, which
reads ``1_0`` as 10 and ``0_625`` as 625, and of non-ASCII digits (``int("٣")`` is 3), where no
data file or tool does."""

from __future__ import annotations

import re

__all__ = ["EMPTY_FIELD", "SEPARATORS", "is_float_text", "text_float", "text_int"]

#: what separates the numbers of a box line (a box file's, ``track --box``'s): commas, blanks
SEPARATORS = re.compile(r"[,\s]+")
#: a value left empty: a comma first or two commas with only blanks between (SEPARATORS skips
#: it, so '10,,20,30,40' would read as the four numbers 10,20,30,40)
EMPTY_FIELD = re.compile(r"^,|,\s*,")


def _plain(s: str) -> str:
    if "_" in s or not s.isascii():
        raise ValueError(f"not a number in a data file: {s!r}")
    return s


def text_float(s: str) -> float:
    """``float(s)`` for a number written in a data file.

    Raises:
        ValueError: ``s`` is not a number, holds an underscore (``1_0``: a typo or a cut
            field, not ten) or a character that is not ASCII.
    """
    return float(_plain(s))


def text_int(s: str) -> int:
    """``int(s)`` for a whole number written in a data file or an option (the same rules as
    :func:`text_float`).

    Raises:
        ValueError: as :func:`text_float`.
    """
    return int(_plain(s))


def is_float_text(s: str) -> bool:
    """Whether ``float(s)`` reads ``s`` (a CSV cell: a number, or a header's word). Underscored
    numbers count as numbers here, so that a row holding one is reported as a bad row, with
    its line, by the reader that parses it with :func:`text_float`."""
    try:
        float(s)
    except ValueError:
        return False
    return True
