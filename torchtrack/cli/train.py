"""``torchtrack train``: train a calibrated Haar / AdaBoost (or SVM) class detector from crops.

Examples::

    # the shipped recipe (paths inside the config are relative to it)
    torchtrack train --config configs/pedestrian.toml -o pedestrian.safetensors

    # your own class: folders of positive and negative crops, 64x64 window, SVM classifier
    torchtrack train --pos crops/dog --neg crops/background --window 64 64 \\
        --classifier svm -o dog.safetensors

    # negatives as random windows of object-free photos, plus two rounds of hard-negative mining
    torchtrack train --pos crops/cars --neg-images photos/no_cars --random-negatives 5000 \\
        --window 40 100 --mining-rounds 2 -o car.safetensors
"""

from __future__ import annotations

import argparse
import sys

from torchtrack.cli._common import integer, number

_EPILOG = """\
examples:
  torchtrack train --config configs/pedestrian.toml -o pedestrian.safetensors
  torchtrack train --pos crops/dog --neg crops/background --window 64 64 -o dog.safetensors
  torchtrack train --pos crops/car --neg-images photos --random-negatives 5000 \\
      --window 40 100 --mining-rounds 2 --features 80 -o car.safetensors

Crops of other sizes are resized to the window (area averaging); colour crops become
grayscale. Unreadable or non-image files are skipped and listed (--strict: fail instead).
Names listed in files given to --exclude (a held-out test split) are never read.
"""


def register(subparsers) -> None:
    from torchtrack.cli._common import add_out, add_progress, seed_value

    p = subparsers.add_parser(
        "train",
        help="train a calibrated class detector from positive and negative crops",
        description=(
            "Train a detector (Chateau et al. 2006): Haar wavelets from integral images, "
            "AdaBoost feature selection, an AdaBoost or SVM classifier, and Platt (or isotonic) "
            "calibration on a held-out 30% of the crops. Writes one model file "
            "(safetensors tensors + JSON metadata, no pickle)."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--config", metavar="TOML", help="training config (see configs/*.toml)")
    add_out(p, "MODEL", "model file to write", required=True)
    p.add_argument(
        "--pos", nargs="+", action="extend", metavar="DIR", help="folders of positive crops"
    )
    p.add_argument(
        "--neg", nargs="+", action="extend", metavar="DIR", help="folders of negative crops"
    )
    p.add_argument(
        "--neg-images",
        nargs="+",
        action="extend",
        metavar="PATH",
        help="object-free images (folders or files)",
    )
    p.add_argument(
        "--random-negatives", type=integer, metavar="N", help="random windows of --neg-images"
    )
    p.add_argument("--window", nargs=2, type=integer, metavar=("H", "W"), help="window size")
    p.add_argument("--name", help="detector name stored in the model")
    p.add_argument("--features", type=integer, metavar="T", help="selected features (default 40)")
    p.add_argument(
        "--bank",
        choices=("haar", "channels"),
        help="feature bank: Chateau's grey Haar bank (default without --config) or integral "
        "channel features with boosted trees",
    )
    p.add_argument("--classifier", choices=("auto", "adaboost", "trees", "svm"))
    p.add_argument("--variant", choices=("discrete", "real", "gentle"), help="boosting variant")
    p.add_argument("--calibration", choices=("platt", "isotonic"))
    p.add_argument(
        "--holdout", type=number, metavar="F", help="calibration hold-out fraction (default 0.3)"
    )
    p.add_argument("--mining-rounds", type=integer, metavar="R", help="hard-negative mining rounds")
    p.add_argument(
        "--exclude", nargs="+", action="extend", metavar="LIST", help="files of names never to use"
    )
    p.add_argument("--mirror", action="store_true", help="add mirror images of the positives")
    p.add_argument("--seed", type=seed_value, help="random seed (default 0)")
    p.add_argument("--strict", action="store_true", help="fail on unreadable or non-image files")
    p.add_argument(
        "--force",
        action="store_true",
        help="train even on too little data (fewer than learn.min_train_per_class = 20 training "
        "or learn.min_calibration_per_class = 10 calibration crops per class, mostly flat "
        "positives); the reasons are recorded in the model",
    )
    add_progress(p)
    p.set_defaults(func=run)


def _overrides(args: argparse.Namespace) -> dict:
    o = {}
    pairs = [
        ("pos", "data.positives"),
        ("neg", "data.negatives"),
        ("neg_images", "data.negative_images"),
        ("random_negatives", "data.random_negatives"),
        ("exclude", "data.exclude"),
        ("window", "window"),
        ("name", "name"),
        ("features", "learn.n_features"),
        ("bank", "features.kind"),
        ("classifier", "learn.classifier"),
        ("variant", "learn.variant"),
        ("calibration", "learn.calibration"),
        ("holdout", "learn.calibration_fraction"),
        ("mining_rounds", "mining.rounds"),
        ("seed", "seed"),
    ]
    for attr, key in pairs:
        v = getattr(args, attr)
        if v is not None:
            o[key] = list(v) if isinstance(v, list) else v
    if args.strict:
        o["data.strict"] = True
    if args.mirror:
        o["data.mirror_positives"] = True
    return o


def run(args: argparse.Namespace) -> int:
    from torchtrack.cli._common import check_output_file, show_progress
    from torchtrack.detect.config import TrainConfig, apply_override, load_train_config
    from torchtrack.detect.model_file import save_detector
    from torchtrack.detect.training import train_detector
    from torchtrack.errors import ConfigError

    check_output_file(args.out, "--out", (".safetensors",))  # before the training, not after
    from torchtrack.cli._common import check_spares_inputs

    check_spares_inputs(
        {"--out": args.out},
        {
            "--exclude": args.exclude or [],
            "--config": args.config,
            "--pos": args.pos or [],
            "--neg": args.neg or [],
            "--neg-images": args.neg_images or [],
        },
    )
    overrides = _overrides(args)
    if args.config:
        cfg = load_train_config(args.config, overrides)
    else:
        if not args.pos:
            raise ConfigError("give --config TOML, or --pos folders (and --neg / --neg-images)")
        cfg = TrainConfig()
        cfg.data.mirror_positives = False
        for k, v in overrides.items():
            apply_override(cfg, k, v)
        cfg.validate()
    if args.features is not None and cfg.classifier() == "trees":
        raise ConfigError(
            f"--features {args.features} sets how many features AdaBoost selects (a Haar bank, "
            "classifier adaboost or svm); boosted trees draw on the whole channel pool "
            "(learn.n_trees in a --config sets their number): leave --features out"
        )
    if args.random_negatives is not None and not cfg.data.negative_images:
        raise ConfigError(
            "--random-negatives draws windows from --neg-images (or data.negative_images): "
            "none were given"
        )
    from torchtrack.cli._common import check_spares_inputs

    d = cfg.data
    check_spares_inputs(
        {"--out": args.out},
        {"--config": args.config, "--pos": list(d.positives), "--neg": list(d.negatives),
         "--neg-images": list(d.negative_images)},
    )  # fmt: skip

    def log(line: str) -> None:
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    det = train_detector(cfg, progress=show_progress(args), log=log, force=args.force)
    path = save_detector(args.out, det)
    held = det.summary["held_out"]
    print(
        f"wrote {path}: {det.feature_index.numel()} features, {cfg.learn.classifier}, "
        f"{cfg.learn.calibration} calibration; held-out detection rate "
        f"{held['dr_at_1pct_fpr']:.3f} at 1% FPR, AUC {held['auc']:.4f}"
    )
    return 0
