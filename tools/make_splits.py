"""Write the fixed held-out test splits of the detector data to ``configs/splits/*.txt``.

Run once (the files are committed); re-running reproduces them byte for byte:

    python tools/make_splits.py [--data ../shared/data]

Rules: 25% of the *source groups* of each folder go to the test split, drawn with
``numpy.random.default_rng(2026)`` over the sorted group names. INRIA crops are grouped by their
source photograph (the name without the trailing letter: ``crop001001a`` and ``crop001001c`` are
two people of one photo), UIUC crops and scene images are their own groups. Training and
calibration read these lists through ``data.exclude`` and never see the files; the benchmarks
in ``tools/bench_detectors.py`` read only them.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np

from torchtrack.io.atomic import write_text_atomic

REPO = Path(__file__).resolve().parents[1]
FRACTION = 0.25
SEED = 2026


def split(names: list[str], group) -> list[str]:
    groups = sorted({group(n) for n in names})
    rng = np.random.default_rng(SEED)
    k = round(FRACTION * len(groups))
    test_groups = {groups[i] for i in rng.permutation(len(groups))[:k]}
    return sorted(n for n in names if group(n) in test_groups)


def write(name: str, files: list[str], what: str, total: int) -> None:
    head = (
        f"# Held-out TEST split: {what}.\n"
        f"# {len(files)} of {total} files; written by tools/make_splits.py (seed {SEED}, "
        f"{FRACTION:.0%} of source groups). Never train or calibrate on these.\n"
    )
    write_text_atomic(REPO / "configs" / "splits" / name, head + "\n".join(files) + "\n")
    print(f"{name}: {len(files)} / {total}")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = ap.parse_args()
    crops = args.data / "detection_crops"
    inria = sorted(p.name for p in (crops / "inria_person_96x160" / "pos").glob("*.png"))
    write(
        "inria_person_test.txt",
        split(inria, lambda n: re.sub(r"[a-z]\.png$", "", n)),
        "INRIA person 96x160 positives (grouped by source photo)",
        len(inria),
    )
    train = crops / "uiuc_car" / "CarData" / "TrainImages"
    pos = sorted(p.name for p in train.glob("pos-*.pgm"))
    neg = sorted(p.name for p in train.glob("neg-*.pgm"))
    write(
        "uiuc_car_test.txt",
        split(pos, str) + split(neg, str),
        "UIUC car train crops, pos-* and neg-*",
        len(pos) + len(neg),
    )
    scenes = sorted(p.name for p in (crops / "scene_negatives").glob("*.jpg"))
    write(
        "scene_negatives_test.txt",
        split(scenes, str),
        "scene_negatives images (pedestrian negatives)",
        len(scenes),
    )


if __name__ == "__main__":
    main()
