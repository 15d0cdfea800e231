"""Fit Chateau et al.'s AR dynamics (eq. 4) on the annotated tracks in shared/data.

Usage:
    python tools/fit_dynamics.py [--data ../shared/data/tracking] [--out torchtrack/data/dynamics_chateau.toml]
    python tools/fit_dynamics.py --structure constant_velocity \
        --out torchtrack/data/dynamics_chateau_cv.toml     # the multi-target tracker's default
    python tools/fit_dynamics.py --structure constant_velocity --noise jitter_corrected \
        --out /tmp/cv_jitter.toml     # how much of that noise is label jitter (1.7 of 4 px)

Reads every OTB / BoBoT ground truth under ``--data`` (with ``torchtrack.io.sequences`` when it
is available, else a small built-in parser), fits A, B, Sigma by least squares
(``torchtrack.filter.fit_chateau_dynamics``; the scale s is relative to each track's first box),
writes them as TOML, and prints a leave-one-sequence-out check: the one-step prediction error of
the fitted model next to constant-position and constant-velocity models.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.filter.dynamics_fit import (  # noqa: E402
    _FREE,
    chateau_states,
    fit_chateau_dynamics,
    save_chateau_toml,
)
from torchtrack.filter.motion import default_chateau_A  # noqa: E402


def _parse(path: Path, corners: bool) -> torch.Tensor:
    rows = []
    for line in path.read_text().splitlines():
        if line.strip():
            rows.append([float(v) for v in re.split(r"[,\s]+", line.strip())[:4]])
    b = torch.tensor(rows, dtype=torch.float64)
    if corners:  # BoBoT x1, y1, x2, y2 (0-based)
        b = torch.cat([b[:, :2], b[:, 2:] - b[:, :2]], 1)
    else:  # OTB x, y, w, h, 1-based
        b = torch.cat([b[:, :2] - 1, b[:, 2:]], 1)
    bad = ~torch.isfinite(b).all(1) | (b[:, 2:] <= 0).any(1)
    b[bad] = math.nan
    return b


def load_tracks(root: Path) -> dict[str, torch.Tensor]:
    try:
        from torchtrack.io.sequences import find_sequences
    except ImportError:
        find_sequences = None
    if find_sequences is not None:
        return {s.name: s.boxes for s in find_sequences(root, on_mismatch="truncate")}
    tracks = {}
    for gt in sorted(root.rglob("groundtruth_rect*.txt")):
        tracks[gt.parent.name] = _parse(gt, corners=False)
    for gt in sorted(root.rglob("gt.txt")):
        tracks[gt.parent.name] = _parse(gt, corners=True)
    return tracks


def one_step_rms(a: torch.Tensor, track: torch.Tensor) -> torch.Tensor:
    """RMS one-step error of cx, cy (pixels) and s under ``X_{t+1} = A X_t``."""
    st, valid = chateau_states(track)
    pair = valid[:-1] & valid[1:]
    if not bool(pair.any()):
        return torch.full((3,), math.nan, dtype=torch.float64)
    x, y = st[:-1][pair], st[1:][pair][:, _FREE]
    return (y - x @ a[_FREE].T).square().mean(0).sqrt()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data" / "tracking")
    ap.add_argument(
        "--out", type=Path, default=REPO / "torchtrack" / "data" / "dynamics_chateau.toml"
    )
    ap.add_argument(
        "--structure",
        choices=("free", "constant_velocity"),
        default="free",
        help="free A (eq. 4 as fitted in the paper) or constant velocity with Sigma fitted",
    )
    ap.add_argument(
        "--noise",
        choices=("residual", "jitter_corrected"),
        default="residual",
        help="Sigma as the residuals' covariance, or with the annotation jitter removed "
        "(median over tracks; constant_velocity only)",
    )
    args = ap.parse_args(argv)
    tracks = load_tracks(args.data)
    fit = fit_chateau_dynamics(list(tracks.values()), structure=args.structure, noise=args.noise)
    cp = torch.eye(6, dtype=torch.float64)  # constant position (c_{t+1} = c_t)
    cp[2, 0], cp[3, 1], cp[5, 4], cp[2, 2], cp[3, 3], cp[5, 5] = 1, 1, 1, 0, 0, 0
    cv = default_chateau_A()
    lines = [
        "| held-out sequence | frames | fitted: cx, cy px, s | const. position | const. velocity |",
        "|---|---|---|---|---|",
    ]
    for name, tr in tracks.items():
        rest = [t for n, t in tracks.items() if n != name]
        a_loo = fit_chateau_dynamics(rest).A
        cells = [
            ", ".join(f"{v:.3g}" for v in one_step_rms(a, tr).tolist()) for a in (a_loo, cp, cv)
        ]
        lines.append(f"| {name} | {tr.shape[0]} | " + " | ".join(cells) + " |")
    table = "\n".join(lines)
    torch.set_printoptions(precision=4, sci_mode=False)
    comment = (
        "Fitted by tools/fit_dynamics.py on the ground truth of "
        f"{len(tracks)} sequences ({', '.join(tracks)}): "
        f"{fit.n_transitions} transitions; s relative to each track's first box; "
        f"structure {args.structure}; noise {args.noise}."
    )
    save_chateau_toml(args.out, fit, comment=comment)
    print(comment)
    print("A =\n", fit.A, "\nA_stderr =\n", fit.A_stderr, "\nSigma =\n", fit.Sigma)
    print("rms one-step residual (cx px, cy px, s):", fit.rms.tolist())
    print("\nLeave-one-sequence-out one-step RMS error:\n" + table)
    print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
