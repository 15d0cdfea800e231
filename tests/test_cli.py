import subprocess
import sys

from torchtrack.cli import COMMANDS, build_parser


def test_help_lists_every_command():
    text = build_parser().format_help()
    for name in COMMANDS:
        assert name in text


def test_building_the_parser_imports_neither_torch_nor_opencv():
    """``torchtrack --help`` stays fast: building the parser (every subcommand's options and
    help text) imports neither torch nor OpenCV, nor the corpus runner that pulls both in
    (they took ~1.8 s of a 1.9 s ``--help``). ``import torchtrack`` alone imports neither, so
    the whole of the check is on what the parser adds. In a fresh interpreter: the test
    process has them imported already."""
    code = (
        "import sys\n"
        "import torchtrack.cli as c\n"
        "c.build_parser().format_help()\n"
        "heavy = ('torch', 'cv2', 'torchtrack.eval.corpus')\n"
        "print(' '.join(m for m in heavy if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == []


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


def test_opencv_warnings_stay_off_the_terminal(tmp_path):
    """OPENCV_LOG_LEVEL is set before the parser is built: building it imports OpenCV (the
    corpus options of track), after which OpenCV no longer reads the variable, so a camera
    that cannot be opened printed two '[ WARN:0@...] global cap_v4l.cpp' lines before the
    error. A fresh interpreter, as from the shell; no camera 97 on any test machine."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "OPENCV_LOG_LEVEL"}
    argv = ["track", "97", "--box", "1,1,9,9", "--tracker", "camshift", "-o", "b.csv"]
    out = subprocess.run(
        [sys.executable, "-m", "torchtrack", *argv],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
    )
    assert out.returncode == 1
    assert out.stderr.splitlines() == [
        "torchtrack track: error: camera index 97 cannot be opened"
    ], out.stderr
    assert list(tmp_path.iterdir()) == []
