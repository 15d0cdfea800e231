"""Train the shipped default detectors into ``torchtrack/models/`` (the recipe behind them).

    python train/default_models.py                 # pedestrian and vehicle
    python train/default_models.py --only vehicle

Each model is ``torchtrack train --config configs/<name>.toml`` with the config's seed: the
held-out test splits in ``configs/splits`` are excluded, 30% of the remaining crops calibrate
the Platt sigmoid, and the summary inside the model records counts and held-out metrics.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from torchtrack.detect import save_detector
from torchtrack.detect.config import load_train_config
from torchtrack.detect.training import train_detector

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--only", nargs="+", choices=["pedestrian", "vehicle"], default=["pedestrian", "vehicle"]
    )
    ap.add_argument("--out", type=Path, default=REPO / "torchtrack" / "models")
    args = ap.parse_args()
    for name in args.only:
        cfg = load_train_config(REPO / "configs" / f"{name}.toml")
        det = train_detector(
            cfg, progress=True, log=lambda s: print(s, file=sys.stderr, flush=True)
        )
        path = save_detector(args.out / f"{name}.safetensors", det)
        held = det.summary["held_out"]
        print(f"{path}: held-out DR@1%FPR {held['dr_at_1pct_fpr']:.3f}, AUC {held['auc']:.4f}")


if __name__ == "__main__":
    main()
