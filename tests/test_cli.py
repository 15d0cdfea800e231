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
