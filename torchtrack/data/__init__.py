"""Small data files shipped with the package: the demo clip and the fitted Chateau dynamics
(``dynamics_chateau.toml``, made by ``tools/fit_dynamics.py``).

Example::

    from torchtrack.data import demo_clip_path
    # torchtrack detect pedestrian "$(python -c 'import torchtrack.data as d; print(d.demo_clip_path())')"
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DATA_DIR", "demo_clip_path"]

DATA_DIR = Path(__file__).resolve().parent


def demo_clip_path() -> Path:
    """Path of the 7-second PETS 2009 S2.L1 demo clip (480x360, 10 fps, 70 frames, mp4v),
    installed with the package (see ``torchtrack/data/README.md`` for its source)."""
    return DATA_DIR / "pets2009_s2l1_demo.mp4"
