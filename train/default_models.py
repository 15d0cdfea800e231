"""Train the shipped default detectors into ``torchtrack/models/`` (the recipe behind them).

    python train/default_models.py                 # pedestrian and vehicle
    python train/default_models.py --only vehicle
    python train/default_models.py --readme-only   # rewrite torchtrack/models/README.md
    python train/default_models.py --box-regression --only pedestrian   # add the box regressor
                                                   # to the model already shipped (no retraining)
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
from torchtrack.detect.config import TrainConfig, load_train_config
from torchtrack.detect.model_file import read_model_metadata
from torchtrack.detect.signing import load_private_key
from torchtrack.detect.train_channels import fit_box_regression
from torchtrack.detect.training import portable_config, train_detector
from torchtrack.io.atomic import write_text_atomic

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHTRACK_DATA", REPO.parent / "shared" / "data"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import test_sets  # noqa: E402  (train/test_sets.py, beside this script)


def test_split_metrics(cfg: TrainConfig, det: Detector) -> dict:
    """Detection rate at 1% FPR (with a 90% bootstrap interval over test images), AUC and the
    calibrated probabilities' ECE on the fixed held-out test set of ``cfg.name``
    (``train/test_sets.py``: windows scored inside their images)."""
    from torchtrack.detect.evaluate import roc_auc
    from torchtrack.learn import calibration_metrics

    ts = test_sets.test_set(cfg.name, DATA)
    pos, neg, pg, ng = test_sets.score_test_set(lambda i, b: det.decision_function(i, b), ts)
    lo, hi = test_sets.bootstrap_dr(pos, neg, pg, ng)
    y = torch.cat((torch.ones(pos.numel()), torch.zeros(neg.numel())))
    out = {
        "set": ts.what + "; never used for training or calibration",
        "positives": int(pos.numel()),
        "negatives": int(neg.numel()),
        "dr_at_1pct_fpr": test_sets.dr_at_fpr(pos, neg, 0.01),
        "dr_interval_90": [lo, hi],
        "auc": roc_auc(torch.cat((pos, neg)), y),
    }
    if det.calibrator is not None:
        pp, pn, _, _ = test_sets.score_test_set(lambda i, b: det.score(i, b), ts)
        out["ece"] = calibration_metrics(torch.cat((pp, pn)).clamp(0, 1), y.long())["ece"]
    return out


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
        '`torchtrack.detect.bundled.load_model("vehicle")`). Both are integral channel feature',
        "detectors (Dollár et al. 2009: box and Haar-like features over colour / gray, gradient",
        "magnitude and oriented-gradient channels, read from integral images at any box size)",
        "with boosted depth-2 trees, rounds of hard-negative mining, a constant soft cascade for",
        "scanning (its threshold per model below) and Chateau et al.'s Platt calibration on a 30% hold-out. Chateau et al.'s grey",
        "Haar bank with 40 AdaBoost-selected stumps is one config key away (`[features] kind =",
        '"haar"`). This file is written by `python train/default_models.py` from the models\' own',
        "metadata.",
        "",
        "Rebuild both (the pedestrian model took 1,471 s and 1,579 s in two runs on 2 busy cores, most",
        "of it the mining scans; the vehicle model under 2 minutes; the seed fixes every random",
        "draw: a rebuild gives the same trees, checked tensor by tensor):",
        "",
        "```",
        "python train/default_models.py            # = torchtrack train --config configs/<name>.toml",
        "python train/default_models.py --box-regression --only pedestrian   # only the box regressor",
        "```",
        "",
        "The pedestrian model's box regressor (`learn.box_regression`) was added on 2026-11-28 to",
        "the model already shipped (`--box-regression`: the same fit that training with the key",
        "runs at its end, with the config's seed; the trees, the calibration and the test-split",
        "numbers unchanged, the recorded config updated to the key;",
        "`tests/detect/test_box_regression.py` refits it from the config and checks the shipped",
        "tensors bit for bit). On 2026-12-02 it was refitted the same way on the crops at every",
        "scale the detector trains on (`data.positive_scales`, 1.0 and 0.5: a window around a",
        "person 48 px tall reads the features of that resolution), where the first fit read them",
        "at their own size only (docs/multi_target.md, box regression at both scales).",
        "",
        "Both files are signed (Ed25519) with the project key; its public half is",
        "`torchtrack-models.pub` here, always trusted by the loader, and its private half is kept",
        "outside the repository (`/work/keys/torchtrack-models.pem` on the project machine). After",
        "retraining, sign again: `python train/default_models.py --sign-key PEM`, or",
        "`torchtrack sign torchtrack/models/NAME.safetensors --key PEM` for a file already",
        "written; `torchtrack sign --check NAME` shows the signer. The tests fail while a bundled",
        "model is unsigned.",
        "",
        "The project key was replaced on 2026-11-28 (key id `245a92be6d1edce7`; before it",
        "`69b32dff516fca49`, whose private half was lost) and again on 2026-12-02 (key id",
        "`66efc4d2e1c06d6c`: the private half of `245a92be6d1edce7` was not on the fresh project",
        "machine either): both files were signed again, the vehicle model's tensors and",
        'description unchanged. A copy signed with an earlier key reports "signed by key ..., which',
        'is not trusted here": it loads where signatures are optional and is refused where they',
        "are required.",
        "",
    ]
    for f in sorted(models_dir.glob("*.safetensors")):
        meta = read_model_metadata(f)
        t = meta["training"]
        c, d, lr, mi = t["config"], t["config"]["data"], t["config"]["learn"], t["config"]["mining"]
        cnt, held = t["counts"], t["held_out"]
        fc = c["features"]
        if fc.get("kind", "haar") == "channels":
            fs = t.get("features", {})
            casc = t.get("cascade", {})
            what = (
                f"channels {fc['channels']} ({fc['orientations']} orientations), {fc['cell']}-px "
                f"cells; a pool of {fs.get('pool', '?')} features ("
                + ("every cell, " if fc["cells"] else "")
                + f"{fc['boxes']} random boxes, {fc['haar']} random Haar filters), "
                f"{fs.get('used', '?')} used by {lr['n_trees']} depth-{lr['tree_depth']} trees "
                f"({lr['variant'] or 'real'} AdaBoost); soft cascade: {casc.get('method')}"
                + (f" at {casc['threshold']:.3g}" if "threshold" in casc else "")
                + (
                    f" (the highest value <= {casc['upper']:g} that rejects at most "
                    f"{casc['miss']:.0%} of the held-out positives at p >= {casc['probability']:g}"
                    f": {casc['held_out_confident_positives_rejected']:.1%} of them, "
                    f"{casc['held_out_positives_rejected']:.1%} of all held-out positives)"
                    if casc.get("method") == "held-out"
                    and "held_out_confident_positives_rejected" in casc
                    else ""
                )
                + f"; {mi['rounds']} mining round(s) of at most {mi['per_round']}"
                + f" (positives also at scales {d.get('positive_scales', [1.0])})"
            )
        else:
            what = (
                f"Haar bank, {lr['n_features']} features, {lr['classifier']} "
                f"({lr['variant']}, {lr.get('n_estimators') or lr['n_features']} rounds), "
                f"{mi['rounds']} hard-negative mining round(s) of {mi['per_round']}"
            )
        lines += [
            f"## `{meta['name']}` ({f.name}, {f.stat().st_size:,} bytes)",
            "",
            f"* Recipe: `torchtrack train --config configs/{meta['name']}.toml -o {f.name}` "
            f"(via `train/default_models.py`), seed {c['seed']}, window {c['window'][0]}x"
            f"{c['window'][1]} (HxW), {what}; {lr['calibration']} calibration on "
            f"{lr['calibration_fraction']:.0%} of the crops; trained in "
            f"{t.get('train_seconds', float('nan')):.0f} s.",
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
            *(
                [
                    "* Mining: false positives per scanned window of the training images (margin "
                    ">= 0) after each round: "
                    + ", ".join(f"{r['fpr']:.1e}" for r in t["rounds"] if "fpr" in r)
                    + f" (mining.target_fpr {mi.get('target_fpr', 0):g}"
                    + (
                        "; not reached: training warned"
                        if t["rounds"] and t["rounds"][-1].get("fpr", 0) > mi.get("target_fpr", 1)
                        else ""
                    )
                    + ")."
                ]
                if any("fpr" in r for r in t["rounds"])
                else []
            ),
            f"* Calibration hold-out: detection rate {held['dr_at_1pct_fpr']:.1%} at 1% FPR, "
            f"AUC {held['auc']:.4f}; Platt NLL {held['calibrated_in_sample']['nll']:.4f}, "
            f"ECE {held['calibrated_in_sample']['ece']:.4f}.",
        ]
        th = t.get("tracking_head")
        by = (th or {}).get("held_out_by_trees", {})
        if th and str(th.get("trees")) in by:
            h = by[str(th["trees"])]
            lines.append(
                f"* Tracking head (what the particle-filter trackers score windows with): the "
                f"first {th['trees']} trees, {h['features']} features, their own Platt "
                f"calibration; calibration hold-out: detection rate {h['dr_at_1pct_fpr']:.1%} "
                f"at 1% FPR, AUC {h['auc']:.4f}, ECE {h['ece']:.4f} (other sizes: "
                + ", ".join(
                    f"{k} trees {v['dr_at_1pct_fpr']:.1%} / AUC {v['auc']:.4f}"
                    for k, v in sorted(by.items(), key=lambda kv: int(kv[0]))
                    if k != str(th["trees"])
                )
                + ")."
            )
        br = meta.get("box_regression")
        if br:
            b = br["summary"]
            lines.append(
                f"* Box regressor (where the object lies in a detection window; scans move each "
                f"kept window by it): ridge regression (alpha {b['alpha']:g}) of the window's "
                f"move on its {meta['training']['features'].get('used', '?')} selected features, "
                f"fitted on {b['windows']:,} jittered windows of the {b['crops']:,} training "
                f"crops read at scales {b.get('scales', [1.0])} (up to {b['jitter'][0]:g} of the "
                f"width, {b['jitter'][1]:g} of the height, scale exp(+-{b['jitter'][2]:g})); on "
                f"{b['held_out_groups']} held-out source "
                "photos the RMS error of (dx, dy, ds) goes from "
                + " / ".join(f"{v:.3f}" for v in b["held_out_rms_before"])
                + " to "
                + " / ".join(f"{v:.3f}" for v in b["held_out_rms_after"])
                + "."
            )
        ts = t.get("test_split")
        if ts and "dr_interval_90" in ts:
            lo, hi = ts["dr_interval_90"]
            lines.append(
                f"* Test split: detection rate **{ts['dr_at_1pct_fpr']:.1%} at 1% FPR** (90% "
                f"bootstrap interval {lo:.1%} - {hi:.1%}), AUC {ts['auc']:.4f}"
                + (f", ECE {ts['ece']:.4f}" if "ece" in ts else "")
                + f"; {ts['set']}."
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
    ap.add_argument(
        "--box-regression",
        action="store_true",
        help="instead of training: fit the box regressor of configs/<name>.toml "
        "(learn.box_regression) on the models already in --out and write them back (the trees, "
        "the calibration and the test-split metrics unchanged: what training with that key "
        "adds at its end, with the same seed)",
    )
    args = ap.parse_args()
    key = load_private_key(args.sign_key) if args.sign_key else None
    if args.box_regression:
        for name in args.only:
            cfg = load_train_config(REPO / "configs" / f"{name}.toml")
            if not cfg.learn.box_regression:
                raise SystemExit(f"configs/{name}.toml does not ask for a box regressor")
            path = args.out / f"{name}.safetensors"
            det = load_detector(path)
            det.summary["config"]["learn"]["box_regression"] = True
            if _norm(det.summary["config"]) != _norm(portable_config(cfg)):
                raise SystemExit(f"{path} was not trained with configs/{name}.toml as it is now")
            det = fit_box_regression(cfg, det)
            save_detector(path, det, signing_key=key).chmod(0o644)
            print(f"{path}: box regressor {det.box_regressor.summary}")
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
    if not args.readme_only and not args.evaluate and not args.box_regression:
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
