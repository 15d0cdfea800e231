"""The commands keep the memory a frame's work frees for the next frame's (glibc)."""

from __future__ import annotations

import subprocess
import sys

import pytest

_FAULTS = """
import resource, sys, torch
from torchtrack.cli import reuse_freed_memory
on = sys.argv[1] == "on" and reuse_freed_memory()
for i in range(30):  # a frame's table of 64 MiB, made, filled and freed
    if i == 20:  # glibc's heap takes a few rounds to settle: the last 10 are counted
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    torch.empty(1 << 23, dtype=torch.float64).fill_(1.0)
print(int(on), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(mode: str) -> tuple[bool, int]:
    out = subprocess.run(
        [sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, check=True
    ).stdout.split()
    return out[0] == "1", int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_freed_blocks_are_reused_instead_of_faulted_in_again():
    """Blocks of 64 MiB made and freed in turn: by default glibc maps each one afresh (a page
    fault per 4 KiB page, ~16,000 a block); with :func:`reuse_freed_memory` the heap's pages
    serve them once it has settled (the last 10 of 30 blocks are counted)."""
    on, faults_on = _faults("on")
    if not on:
        pytest.skip("not glibc: mallopt is not available, nothing is changed")
    _, faults_off = _faults("off")
    assert faults_off > 9 * 16_000
    assert faults_on < 16_000
