"""``tools/loso_multi.py``'s argument checks (the grid itself runs for minutes: not a test)."""

import importlib.util
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("loso_multi", REPO / "tools" / "loso_multi.py")
loso = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(loso)


def test_set_holds_other_keys_typed_like_the_config():
    assert loso.parse_fixed("", "motion_noise") == {}
    fixed = loso.parse_fixed("detection_proposal=0.1,confirm_hits=3", "motion_noise")
    assert fixed == {"detection_proposal": 0.1, "confirm_hits": 3}


@pytest.mark.parametrize(
    "spec, grid_key, message",
    [
        ("motion_noise=0.5", "motion_noise", "grid's key"),
        ("no_such_key=1", "motion_noise", "no_such_key"),
        ("detection_proposal=2", "motion_noise", "detection_proposal"),
    ],
)
def test_set_refuses_the_grid_key_unknown_keys_and_bad_values(spec, grid_key, message):
    with pytest.raises(SystemExit, match=message):
        loso.parse_fixed(spec, grid_key)
