"""``tools/fuzz_tracks.py``: random track streams through the smoother and the identity
repair keep every frame, once, in order, with no identity twice on a frame; the streams that
raised a KeyError in the identity repair (a swap that dropped encounters judged on the same
frame) are replayed."""

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("fuzz_tracks", REPO / "tools" / "fuzz_tracks.py")
fuzz = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fuzz)


@pytest.mark.parametrize("trial", [23, 65, 278, 493, 500, *range(8)])
def test_random_streams_come_out_whole(trial):
    assert fuzz.stream_trial(trial) is None


def test_a_broken_invariant_is_reported(monkeypatch):
    """The check can fail: a smoother that drops the last frame is caught."""
    real = fuzz.TrackSmoother

    class Dropping(real):
        def flush(self):
            return super().flush()[:-1]

    monkeypatch.setattr(fuzz, "TrackSmoother", Dropping)
    why = fuzz.stream_trial(0)
    assert why is not None and "frames out of order, lost or given twice" in why


def test_the_tool_needs_something_to_run():
    with pytest.raises(SystemExit):
        fuzz.main([])
