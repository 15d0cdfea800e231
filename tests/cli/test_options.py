"""How the subcommands' options are read (argparse level, no work done)."""

from __future__ import annotations

import pytest

from torchtrack.cli import build_parser

REPEATED = [
    (["train", "-o", "m.safetensors", "--pos", "a", "--pos", "b", "c"], "pos", ["a", "b", "c"]),
    (["train", "-o", "m.safetensors", "--neg", "a", "--neg", "b"], "neg", ["a", "b"]),
    (["train", "-o", "m.safetensors", "--neg-images", "a", "--neg-images", "b"], "neg_images",
     ["a", "b"]),
    (["train", "-o", "m.safetensors", "--exclude", "a", "--exclude", "b"], "exclude", ["a", "b"]),
    (["calibrate", "m", "--pos", "a", "--pos", "b"], "pos", ["a", "b"]),
    (["calibrate", "m", "--neg", "a", "--neg", "b"], "neg", ["a", "b"]),
    (["eval", "--sequences", "a", "--sequences", "b"], "sequences", ["a", "b"]),
    (["eval", "--trackers", "mil", "--trackers", "kcf"], "trackers", ["mil", "kcf"]),
    (["eval", "--mot", "a", "--mot", "b"], "mot", ["a", "b"]),
    (["eval", "--results", "a", "--results", "b"], "results", ["a", "b"]),
    (["eval", "--gt", "a", "--gt", "b"], "gt", ["a", "b"]),
]  # fmt: skip


@pytest.mark.parametrize("argv, dest, want", REPEATED, ids=[f"{a[0]}-{d}" for a, d, _ in REPEATED])
def test_a_repeated_list_option_adds_to_the_list(argv, dest, want):
    """`train --pos a --pos b` trained on b alone: argparse kept the last --pos and dropped the
    folders of the first without a word (so did every list option of train, calibrate, eval)."""
    assert getattr(build_parser().parse_args(argv), dest) == want


def test_a_list_option_default_is_not_shared_between_runs():
    """eval --gt defaults to []: extending it must not change the default of the next parse."""
    parser = build_parser()
    assert parser.parse_args(["eval", "--gt", "a"]).gt == ["a"]
    assert parser.parse_args(["eval"]).gt == []
