"""The kinds of per-source output file of a corpus run (:mod:`torchtrack.eval.corpus`).

A module of its own, importing nothing heavy, so that the ``torchtrack track`` parser can list
the kinds in its help without importing the corpus runner (and through it OpenCV and torch).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OutputKind:
    """One kind of per-source output file.

    Attributes:
        name: what the user asks for (``"csv"``).
        suffix: the file's ending after the source's name (``".csv"``, ``".mot.txt"``); the
            temporary file ends with it too, so writers that pick a format from the extension
            (``cv2.VideoWriter``) still work.
        keyword: the job's keyword argument that receives the path to write (``"out"``).
    """

    name: str
    suffix: str
    keyword: str
