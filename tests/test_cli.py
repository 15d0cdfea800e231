import subprocess
import sys

from torchtrack.cli import COMMANDS, build_parser


def test_help_lists_every_command():
    text = build_parser().format_help()
    for name in COMMANDS:
        assert name in text


def test_module_entry_point_runs():
    out = subprocess.run(
        [sys.executable, "-m", "torchtrack", "--version"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert out.stdout.startswith("torchtrack ")


def test_subcommands_spell_common_options_alike():
    """Every subcommand takes -o/--out (old spelling --output still parses), --no-progress
    and -q/--quiet (issue 11: one spelling across the five subcommands)."""
    from torchtrack.cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    for name in COMMANDS:
        p = sub.choices[name]
        opts = {s for a in p._actions for s in a.option_strings}
        assert {"-o", "--out", "--no-progress", "-q", "--quiet"} <= opts, name
        dest = {a.dest for a in p._actions if "--out" in a.option_strings}
        assert dest == {"out"}, name
    assert "--output" in {s for a in sub.choices["detect"]._actions for s in a.option_strings}


def test_detect_accepts_the_demo_clip(tmp_path):
    import json

    from torchtrack.cli import main

    out = tmp_path / "d.jsonl"
    code = main(
        [
            "detect",
            "pedestrian",
            "demo",
            "--out",
            str(out),
            "--max-frames",
            "1",
            "--no-progress",
            "--min-scale",
            "0.5",
            "--threshold",
            "0.9",
        ]
    )
    assert code == 0
    rec = json.loads(out.read_text().splitlines()[0])
    assert rec["frame"] == 0 and rec["width"] == 480 and rec["height"] == 360
