"""Train the shipped default detectors into ``torchtrack/models/`` (the recipe behind them).

    python train/default_models.py                 # pedestrian and vehicle
    python train/default_models.py --only vehicle
    python train/default_models.py --readme-only   # rewrite torchtrack/models/README.md
    python train/default_models.py --sign-key /work/keys/torchtrack-models.pem   # and sign them

The bundled models are signed (Ed25519, :mod:`torchtrack.detect.signing`) with the project key
whose public half ships as ``torchtrack/models/torchtrack-models.pub``; its private half lives
outside the repository (on the project machine ``/work/keys/torchtrack-models.pem``) and is
never committed. ``--sign-key`` signs each model as it is written; a model written without it
is signed afterwards with ``torchtrack sign torchtrack/models/NAME.safetensors --key PEM``.
``tests/detect/test_signing.py`` fails while a bundled model is unsigned.

Each model is ``torchtrack train --config configs/<name>.toml`` with the config's seed: the
held-out test splits in ``configs/splits`` are excluded, 30% of the remaining crops calibrate
the Platt sigmoid, and the summary inside the model records counts and held-out metrics.
This script adds ``summary["test_split"]``: detection rate at 1% FPR and AUC on the fixed test
split (files listed in the config's ``data.exclude`` lists, never read by training or
calibration), then writes the model and ``torchtrack/models/README.md`` from the models'
metadata.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

from torchtrack.detect import Detector, load_detector, save_detector
from torchtrack.detect.config import TrainConfig, load_train_config, read_name_list
from torchtrack.detect.evaluate import crop_scores, detection_rate_at_fpr, roc_auc
from torchtrack.detect.model_file import read_model_metadata
from torchtrack.detect.signing import load_private_key
from torchtrack.detect.training import portable_config, train_detector
from torchtrack.io.atomic import write_text_atomic
from torchtrack.io.crops import (
    CropSet,
    list_image_files,
    load_crops,
    load_images,
    mirror,
    sample_windows,
)

REPO = Path(__file__).resolve().parents[1]
TEST_WINDOWS = 5000  # random windows of the held-out negative images (seed 1)


def _split_entry(entry: str) -> tuple[str, str | None]:
    p = Path(entry)
    if any(c in p.name for c in "*?["):
        return str(p.parent), p.name
    return entry, None


def test_split_metrics(cfg: TrainConfig, det: Detector) -> dict:
    """Detection rate at 1% FPR and AUC on the held-out test split of ``cfg``.

    Positives: the test-split crops of ``data.positives`` (+ mirror images when the config
    mirrors). Negatives: the test-split crops of ``data.negatives`` (+ mirrors) and
    ``TEST_WINDOWS`` random windows of the test-split ``data.negative_images``.
    """
    names: set[str] = set()
    for f in cfg.data.exclude:
        names |= read_name_list(f)
    window = (int(cfg.window[0]), int(cfg.window[1]))
    d = cfg.data
    region = tuple(d.region) if d.region else None
    crop_size = tuple(d.crop_size) if d.crop_size else None
    pos = CropSet.concat(
        [
            load_crops(folder, window, region=region, crop_size=crop_size, only=names, pattern=pat)
            for folder, pat in map(_split_entry, d.positives)
        ]
    )
    if d.mirror_positives:
        pos = mirror(pos)
    negs = [
        load_crops(folder, window, only=names, pattern=pat)
        for folder, pat in map(_split_entry, d.negatives)
    ]
    if d.mirror_negatives:
        negs = [mirror(n) for n in negs]
    img_paths: list[Path] = []
    for e in d.negative_images:
        p = Path(e)
        files = list_image_files(p)[0] if p.is_dir() else [p]
        img_paths += [f for f in files if f.name in names]
    n_windows = 0
    if img_paths:
        images, sources, _ = load_images(img_paths)
        gen = torch.Generator().manual_seed(1)
        negs.append(
            sample_windows(
                images,
                sources,
                window,
                TEST_WINDOWS,
                min_scale=d.negative_min_scale,
                max_scale=d.negative_max_scale,
                generator=gen,
            )
        )
        n_windows = TEST_WINDOWS
    neg = CropSet.concat(negs)
    m = torch.cat((crop_scores(det, pos.images), crop_scores(det, neg.images)))
    y = torch.cat((torch.ones(len(pos)), torch.zeros(len(neg))))
    dr, fpr, _ = detection_rate_at_fpr(m, y, 0.01)
    return {
        "set": "fixed test split (configs/splits), never used for training or calibration",
        "positives": len(pos),
        "negatives": len(neg),
        "negative_windows": n_windows,
        "negative_images": len(img_paths),
        "dr_at_1pct_fpr": dr,
        "fpr": fpr,
        "auc": roc_auc(m, y),
    }


def _norm(v):
    """Config dict with paths normalised (``a/../b`` -> ``b``) for comparison."""
    if isinstance(v, dict):
        return {k: _norm(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_norm(x) for x in v]
    return os.path.normpath(v) if isinstance(v, str) and "/" in v else v


def _rel(p: str, root: str | None = None) -> str:
    """A recorded data path shown relative to the shared data folder. Newer models record paths
    relative to their data root (``data.root``, e.g. ``detection_crops``); older ones absolute."""
    if not Path(p).is_absolute():
        return f"../shared/data/{root}/{p}" if root else p
    s = str(Path(p).resolve()) if "*" not in p else str(Path(p).parent.resolve() / Path(p).name)
    key = "/shared/data/"
    return "../shared/data/" + s.split(key, 1)[1] if key in s else s


def write_readme(models_dir: Path) -> Path:
    """``models_dir/README.md`` from the metadata of the model files in ``models_dir``."""
    lines = [
        "# Bundled detectors",
        "",
        "Usable by name wherever a model path is accepted (`torchtrack detect pedestrian ...`,",
        '`torchtrack.detect.bundled.load_model("vehicle")`). Both are Chateau et al. (2006)',
        "detectors: Haar wavelets from integral images, 40 AdaBoost-selected features, boosted",
        "stumps on them (variant and rounds per model below), Platt calibration on a 30% hold-out.",
        "This file is written by",
        "`python train/default_models.py` from the models' own metadata.",
        "",
        "Rebuild both (about 25 minutes on 2 busy cores; the seed fixes every random draw):",
        "",
        "```",
        "python train/default_models.py            # = torchtrack train --config configs/<name>.toml",
        "```",
        "",
        "Both files are signed (Ed25519) with the project key; its public half is",
        "`torchtrack-models.pub` here, always trusted by the loader, and its private half is kept",
        "outside the repository (`/work/keys/torchtrack-models.pem` on the project machine). After",
        "retraining, sign again: `python train/default_models.py --sign-key PEM`, or",
        "`torchtrack sign torchtrack/models/NAME.safetensors --key PEM` for a file already",
        "written; `torchtrack sign --check NAME` shows the signer. The tests fail while a bundled",
        "model is unsigned.",
        "",
    ]
    for f in sorted(models_dir.glob("*.safetensors")):
        meta = read_model_metadata(f)
        t = meta["training"]
        c, d, lr, mi = t["config"], t["config"]["data"], t["config"]["learn"], t["config"]["mining"]
        cnt, held = t["counts"], t["held_out"]
        lines += [
            f"## `{meta['name']}` ({f.name}, {f.stat().st_size:,} bytes)",
            "",
            f"* Recipe: `torchtrack train --config configs/{meta['name']}.toml -o {f.name}` "
            f"(via `train/default_models.py`), seed {c['seed']}, window {c['window'][0]}x"
            f"{c['window'][1]} (HxW), {lr['n_features']} features, {lr['classifier']} "
            f"({lr['variant']}, {lr.get('n_estimators') or lr['n_features']} rounds), "
            f"{lr['calibration']} calibration on {lr['calibration_fraction']:.0%}"
            f" of the crops, {mi['rounds']} hard-negative mining round(s) of {mi['per_round']}.",
            "* Positives: "
            + ", ".join(f"`{_rel(p, d.get('root'))}`" for p in d["positives"])
            + (" + mirror images" if d["mirror_positives"] else "")
            + (f"; region {d['region']} of {d['crop_size']} crops" if d["region"] else "")
            + ".",
            "* Negatives: "
            + (", ".join(f"`{_rel(p, d.get('root'))}`" for p in d["negatives"]) or "none as crops")
            + (" + mirror images" if d["negatives"] and d["mirror_negatives"] else "")
            + (
                f"; {d['random_negatives']} random windows and mined windows of "
                f"{len(d['negative_images'])} negative image entries "
                f"({', '.join(sorted({Path(_rel(p, d.get('root'))).parent.name for p in d['negative_images']}))})"
                if d["negative_images"]
                else ""
            )
            + ".",
            "* Held-out test split (never read by training or calibration): "
            + ", ".join(f"`configs/splits/{n}`" for n in t["excluded_lists"])
            + "; the calibration hold-out's source files are listed in the model's metadata "
            "(`training.calibration_sources`).",
            f"* Training counts: {cnt['positives_train']} positive / {cnt['negatives_train']} "
            f"negative crops (incl. {cnt['hard_negatives']} mined), calibration "
            f"{cnt['positives_calibration']} / {cnt['negatives_calibration']}.",
            f"* Calibration hold-out: detection rate {held['dr_at_1pct_fpr']:.1%} at 1% FPR, "
            f"AUC {held['auc']:.4f}; Platt NLL {held['calibrated_in_sample']['nll']:.4f}, "
            f"ECE {held['calibrated_in_sample']['ece']:.4f}.",
        ]
        ts = t.get("test_split")
        if ts:
            lines.append(
                f"* Test split: detection rate **{ts['dr_at_1pct_fpr']:.1%} at 1% FPR**, AUC "
                f"{ts['auc']:.4f} ({ts['positives']} positive crops incl. mirrors, "
                f"{ts['negatives']} negatives"
                + (
                    f" incl. {ts['negative_windows']} random windows of {ts['negative_images']} "
                    "held-out images"
                    if ts["negative_windows"]
                    else ""
                )
                + ")."
            )
        lines.append("")
    path = models_dir / "README.md"
    write_text_atomic(path, "\n".join(lines))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--only", nargs="+", choices=["pedestrian", "vehicle"], default=["pedestrian", "vehicle"]
    )
    ap.add_argument("--out", type=Path, default=REPO / "torchtrack" / "models")
    ap.add_argument("--readme-only", action="store_true", help="only rewrite README.md")
    ap.add_argument(
        "--evaluate",
        nargs="+",
        type=Path,
        metavar="MODEL",
        help="instead of training: add the test-split metrics to models already trained with "
        "`torchtrack train --config configs/<name>.toml` (the config must match) and install them",
    )
    ap.add_argument(
        "--sign-key",
        metavar="PEM",
        help="Ed25519 private key to sign the written models with (the project key; never "
        "commit it)",
    )
    args = ap.parse_args()
    key = load_private_key(args.sign_key) if args.sign_key else None
    for f in args.evaluate or []:
        det = load_detector(f)
        cfg = load_train_config(REPO / "configs" / f"{det.name}.toml")
        recorded = _norm(det.summary.get("config"))
        if recorded not in (_norm(cfg.to_dict()), _norm(portable_config(cfg))):
            raise SystemExit(f"{f} was not trained with configs/{det.name}.toml as it is now")
        det.summary["test_split"] = test_split_metrics(cfg, det)
        path = save_detector(args.out / f"{det.name}.safetensors", det, signing_key=key)
        path.chmod(0o644)
        print(f"{path}: test split {det.summary['test_split']}")
    if not args.readme_only and not args.evaluate:
        for name in args.only:
            cfg = load_train_config(REPO / "configs" / f"{name}.toml")
            det = train_detector(
                cfg, progress=True, log=lambda s: print(s, file=sys.stderr, flush=True)
            )
            det.summary["test_split"] = test_split_metrics(cfg, det)
            path = save_detector(args.out / f"{name}.safetensors", det, signing_key=key)
            path.chmod(0o644)
            held, ts = det.summary["held_out"], det.summary["test_split"]
            print(
                f"{path}: calibration hold-out DR@1%FPR {held['dr_at_1pct_fpr']:.3f}, AUC "
                f"{held['auc']:.4f}; test split DR@1%FPR {ts['dr_at_1pct_fpr']:.3f}, AUC "
                f"{ts['auc']:.4f}"
            )
    print(f"wrote {write_readme(args.out)}")


if __name__ == "__main__":
    main()
