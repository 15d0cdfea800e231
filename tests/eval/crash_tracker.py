"""A tracker module imported by spawned workers in the tests (``modules=`` / ``--import``)."""

from __future__ import annotations

import os

from torchtrack.track.base import Tracker, TrackState, register_tracker


class Crash(Tracker):
    """Kills its process on the second update, like a segfault in native code would."""

    name = "test-crash"

    def _init(self, frame, boxes):
        self.box, self.n = boxes[0].clone(), 0
        return TrackState.single(self.box)

    def _update(self, frame):
        self.n += 1
        if self.n == 2:
            os._exit(3)
        return TrackState.single(self.box)


register_tracker("test-crash", Crash)


class DieOnce(Crash):
    """Kills its process on the second update the first time it ever runs (``marker``, a file
    path, records that it did), then tracks like a static box: a worker dying once."""

    name = "test-die-once"

    def __init__(self, marker: str) -> None:
        super().__init__()
        self.marker = marker

    def _update(self, frame):
        self.n += 1
        if self.n == 2 and not os.path.exists(self.marker):
            with open(self.marker, "w") as f:
                f.write(f"{os.getpid()}\n")
            os._exit(3)
        return TrackState.single(self.box)


register_tracker("test-die-once", DieOnce)
