"""``torchtrack calibrate``: Platt (or isotonic) calibration of a detector or of a score file.

Two inputs (Chateau et al. 2006, section 2.4):

* a model file plus folders of labelled calibration crops (not used in training): the crops are
  scored by the detector, a calibrator is fitted to the margins and written into the model
  (atomically; ``-o`` writes a copy) or, with ``--json``, to a JSON file (with both ``-o`` and
  ``--json``, to both);
* a CSV of ``score,label`` rows (header optional: it names both columns, or neither and the
  first two are read, or one where those put it; labels two distinct numbers, the larger is
  positive): the calibrator is written to ``--json``.

It prints NLL, Brier score and ECE (equal-width bins, default 15) before calibration, after it
on the calibration data itself, and after it by 5-fold cross-validation (the honest estimate),
and can draw a reliability diagram (``--plot``). ``--prior P`` moves the fitted map to data
whose positives are a share ``P`` (:func:`torchtrack.learn.with_prior`; a scan's windows are
mostly background, crops for calibration often half positives) and weights every metric and
the diagram to that share (:func:`torchtrack.learn.prior_weights`).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from torchtrack.cli._common import integer, number

_EPILOG = """\
examples:
  # recalibrate a detector on held-out labelled crops, in place, with a reliability plot
  torchtrack calibrate pedestrian.safetensors --pos calib/pos --neg calib/neg \\
      --plot reliability.png

  # INRIA-style crops (96x160 with the person in the central 64x128 box)
  torchtrack calibrate pedestrian.safetensors --pos calib/persons --neg calib/background \\
      --crop-size 160 96 --region 16 16 64 128

  # isotonic instead of Platt, written to a new model file
  torchtrack calibrate car.safetensors --pos calib/cars --neg calib/background \\
      --method isotonic -o car-isotonic.safetensors

  # any classifier's scores: a CSV with columns score,label (header optional)
  torchtrack calibrate --scores scores.csv --json platt.json --plot reliability.png

  # probabilities for data where 3% are positives, calibrated on balanced crops
  torchtrack calibrate --scores scores.csv --json platt.json --prior 0.03

"before" is the model's current calibration when it has one; otherwise the logistic
1/(1+exp(-m)) of the raw margin (or the scores themselves when all lie in [0, 1]).
ECE uses equal-width probability bins (--bins, default 15).
"""

JSON_FORMAT = "torchtrack-calibration"
JSON_VERSION = 1


def register(subparsers) -> None:
    from torchtrack.cli._common import add_out, add_progress, add_trust, seed_value

    p = subparsers.add_parser(
        "calibrate",
        help="fit Platt / isotonic calibration for a detector or a CSV of scores",
        description=(
            "Fit P(positive | m) = 1 / (1 + exp(A m + B)) (Platt, Chateau et al. eq. 5-8) or an "
            "isotonic map to a detector's margins on labelled crops, or to a CSV of scores and "
            "labels; print NLL / Brier / ECE before and after; optionally plot reliability."
        ),
        epilog=_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "model",
        nargs="?",
        metavar="MODEL",
        help="detector model file to calibrate, or a bundled name (pedestrian, vehicle) with -o OUT",
    )
    p.add_argument(
        "--pos",
        nargs="+",
        action="extend",
        metavar="DIR",
        help="folders of positive calibration crops",
    )
    p.add_argument(
        "--neg",
        nargs="+",
        action="extend",
        metavar="DIR",
        help="folders of negative calibration crops",
    )
    p.add_argument(
        "--region",
        nargs=4,
        type=integer,
        metavar=("X", "Y", "W", "H"),
        help="object box inside each crop (with --crop-size), e.g. INRIA 96x160: 16 16 64 128",
    )
    p.add_argument(
        "--crop-size",
        nargs=2,
        type=integer,
        metavar=("H", "W"),
        help="crop size --region refers to",
    )
    p.add_argument("--scores", metavar="CSV", help="CSV of score,label rows instead of a model")
    p.add_argument("--method", choices=("platt", "isotonic"), default="platt")
    p.add_argument("--json", metavar="OUT", help="write the calibration to this JSON file")
    add_out(p, "MODEL", "write the calibrated model here (default: MODEL itself)")
    p.add_argument("--plot", metavar="PNG", help="write a reliability diagram")
    p.add_argument(
        "--prior",
        type=number,
        metavar="P",
        help="share of positives where the probabilities will be used (e.g. among the windows "
        "a scan scores), in (0, 1): the fitted map's log-odds move by logit(P) - logit(the "
        "calibration data's share) and the metrics are weighted to that share (default: the "
        "calibration data's own share)",
    )
    p.add_argument(
        "--bins", type=integer, default=15, help="ECE / diagram bins, 1 to 1000 (default 15)"
    )
    p.add_argument("--seed", type=seed_value, default=0, help="seed of the CV folds (default 0)")
    p.add_argument("--strict", action="store_true", help="fail on unreadable or non-image files")
    p.add_argument(
        "--min-per-class",
        type=integer,
        default=10,
        metavar="N",
        help="fewest positive and negative samples to calibrate on (default 10; Platt's two "
        "parameters from fewer are noise)",
    )
    p.add_argument(
        "--force", action="store_true", help="calibrate even below --min-per-class samples"
    )
    add_progress(p)
    add_trust(p)
    p.set_defaults(func=run)


# ----------------------------------------------------------------------------- inputs


def read_scores_csv(path: str | Path) -> tuple[Any, Any]:
    """Read ``score,label`` rows.

    A first line whose first two cells are not numbers is a header (one number and one word is
    an error: a data row with a typo); it may name the columns ``score`` and ``label`` in any
    order (other columns are ignored), otherwise the first two columns are used (a header
    naming only one of them must name it where those put it: ``score`` first or ``label``
    second). Blank lines and lines starting with ``#`` are skipped.

    Returns:
        ``(scores (n,) float64, labels (n,) float64)`` torch tensors.

    Raises:
        DataError: the file is missing or empty, a first line that is half numbers, or rows
            are bad (up to 10 listed by line number: wrong column count, non-numbers, NaN / inf).
    """
    import csv
    import math

    import torch

    from torchtrack.errors import DataError

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise DataError(f"cannot read score file {str(p)!r}: {exc}") from None
    except UnicodeDecodeError:
        raise DataError(f"score file {str(p)!r} is not UTF-8 text") from None
    try:
        rows = [
            (i, r)
            for i, r in enumerate(csv.reader(text.splitlines()), start=1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")
        ]
    except csv.Error as exc:  # e.g. a field past the csv module's size limit
        raise DataError(f"score file {str(p)!r} is not a CSV of scores: {exc}") from None
    if not rows:
        raise DataError(f"score file {str(p)!r} has no rows")
    si, li = 0, 1
    first = [c.strip() for c in rows[0][1]]
    from torchtrack.io.text import is_float_text, text_float

    numeric = [is_float_text(c) for c in first[:2]]
    if any(numeric) and not all(numeric):
        # one number and one word: a first data row with a typo ('0.9O,1'), dropped as a
        # header without a word
        k = numeric.index(True)
        raise DataError(
            f"score file {str(p)!r} line {rows[0][0]}: {','.join(first)[:60]!r} is neither a "
            f"header (its column {k + 1} {first[k]!r} is a number) nor a row of numbers "
            f"(column {2 - k} {first[1 - k]!r} is not)"
        )
    if not all(numeric):
        names = [c.lower() for c in first]
        if "score" in names and "label" in names:
            si, li = names.index("score"), names.index("label")
        else:  # read by position: a column named otherwise there ('frame,score,y') is refused
            for name, other, pos in (("score", "label", 0), ("label", "score", 1)):
                if name in names and names.index(name) != pos:
                    raise DataError(
                        f"score file {str(p)!r}: its header {','.join(first)!r} names column "
                        f"{names.index(name) + 1} {name!r} and no column {other!r}, so the "
                        "first two columns would be read as score, label: name both columns "
                        "'score' and 'label'"
                    ) from None
        rows = rows[1:]
    scores, labels, bad = [], [], []
    for line, r in rows:
        if len(r) <= max(si, li):
            bad.append(f"line {line}: expected at least {max(si, li) + 1} columns, got {len(r)}")
            continue
        try:
            s, lab = text_float(r[si]), text_float(r[li])
        except ValueError:
            bad.append(f"line {line}: not numbers: {','.join(r)[:60]!r}")
            continue
        if not (math.isfinite(s) and math.isfinite(lab)):
            bad.append(f"line {line}: non-finite value (score {r[si]!r}, label {r[li]!r})")
            continue
        scores.append(s)
        labels.append(lab)
    if bad:
        more = f"\n  ... and {len(bad) - 10} more" if len(bad) > 10 else ""
        raise DataError(
            f"{len(bad)} bad row(s) in {str(p)!r} (expected score,label):\n  "
            + "\n  ".join(bad[:10])
            + more
        )
    if not scores:
        raise DataError(f"score file {str(p)!r} has a header but no data rows")
    return torch.tensor(scores, dtype=torch.float64), torch.tensor(labels, dtype=torch.float64)


def crop_margins(
    det: Any,
    folders: list[str],
    *,
    strict: bool,
    progress: bool,
    region: tuple[int, int, int, int] | None = None,
    crop_size: tuple[int, int] | None = None,
    chunk: int = 256,
):
    """Detector margins ``(n,)`` float64 of every crop in ``folders`` (whole-window boxes).

    Returns:
        ``(margins, n_skipped)``.
    """
    import torch

    from torchtrack.io.crops import CropSet, load_crops

    sets = [
        load_crops(
            f, det.window, region=region, crop_size=crop_size, strict=strict, progress=progress
        )
        for f in folders
    ]
    crops = CropSet.concat(sets)
    for path, why in crops.skipped:
        print(f"warning: skipped {path}: {why}", file=sys.stderr)
    h, w = det.window
    out = []
    for i in range(0, len(crops), chunk):
        imgs = crops.images[i : i + chunk]
        boxes = torch.tensor([0.0, 0.0, float(w), float(h)]).expand(imgs.shape[0], 1, 4)
        out.append(det.decision_function(imgs, boxes)[:, 0].to(torch.float64))
    return torch.cat(out), len(crops.skipped)


# ---------------------------------------------------------------------------- metrics


def cv_probabilities(
    method: str, s: Any, y01: Any, k: int = 5, seed: int = 0, prior: float | None = None
) -> Any:
    """Out-of-fold calibrated probabilities ``(n,)`` (stratified ``k`` folds), or ``None`` when a
    class has fewer than ``k`` samples; with ``prior``, each fold's calibrator moved to that
    share of positives from its training part's (:func:`~torchtrack.learn.with_prior`)."""
    import torch

    from torchtrack.learn import make_calibrator, with_prior

    g = torch.Generator().manual_seed(seed)
    fold = torch.empty(s.shape[0], dtype=torch.long)
    for c in (0, 1):
        idx = (y01 == c).nonzero().squeeze(1)
        if idx.numel() < k:
            return None
        fold[idx[torch.randperm(idx.numel(), generator=g)]] = torch.arange(idx.numel()) % k
    p = torch.empty_like(s)
    import warnings

    for f in range(k):
        tr, te = fold != f, fold == f
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            cal = make_calibrator(method).fit(s[tr], y01[tr])
        if prior is not None:
            cal = with_prior(cal, prior, float(y01[tr].double().mean()))
        p[te] = cal.predict_proba(s[te])
    return p


def _format_table(rows: list[tuple[str, dict[str, float]]], bins: int) -> str:
    width = max(len(r[0]) for r in rows) + 2
    head = f"{'':<{width}}{'NLL':>9}{'Brier':>9}{f'ECE({bins})':>9}"
    lines = [head]
    for name, m in rows:
        lines.append(f"{name:<{width}}{m['nll']:>9.4f}{m['brier']:>9.4f}{m['ece']:>9.4f}")
    return "\n".join(lines)


# -------------------------------------------------------------------------------- run


def run(args: argparse.Namespace) -> int:
    import json
    import warnings

    import torch

    from torchtrack.cli._common import show_progress
    from torchtrack.errors import ConfigError
    from torchtrack.io.atomic import write_text_atomic
    from torchtrack.learn import (
        calibration_metrics,
        calibrator_to_dict,
        make_calibrator,
        reliability_diagram,
    )
    from torchtrack.learn._base import as_binary_labels

    if args.model is None and args.scores is None:
        raise ConfigError(
            "nothing to calibrate: give a MODEL (with --pos and --neg) or --scores CSV"
        )
    if args.model is not None and args.scores is not None:
        raise ConfigError("give either a MODEL (with --pos and --neg) or --scores CSV, not both")
    from torchtrack.learn.calibration import MAX_BINS

    if not 1 <= args.bins <= MAX_BINS:
        raise ConfigError(f"--bins must be in [1, {MAX_BINS}], got {args.bins}")
    if args.min_per_class < 1:
        raise ConfigError(f"--min-per-class must be >= 1, got {args.min_per_class}")
    if args.prior is not None:  # before any crop is read
        from torchtrack.learn.calibration import check_prior

        check_prior(args.prior, "--prior")
    from torchtrack.cli._common import check_distinct, check_output_file

    check_output_file(args.json, "--json")
    check_output_file(args.plot, "--plot", (".png", ".pdf", ".svg"))
    check_distinct({"--json": args.json, "--plot": args.plot, "--out": args.out})
    check_distinct({"--json": args.json, "--plot": args.plot, "MODEL": args.model})
    check_distinct({"--json": args.json, "--plot": args.plot, "--scores": args.scores})
    from torchtrack.cli._common import check_spares_inputs

    outs = {"--json": args.json, "--plot": args.plot, "--out": args.out}
    # --out may be MODEL itself: the calibration is written into the model, atomically
    check_spares_inputs(outs, {"--pos": args.pos or [], "--neg": args.neg or []})
    check_spares_inputs({"--json": args.json, "--plot": args.plot}, {"MODEL": args.model})
    # a model file, as train writes: -o cal.json (meant --json) got the binary model
    check_output_file(args.out, "--out", (".safetensors",))
    det = None
    if args.scores is not None:
        if args.pos or args.neg or args.out:
            raise ConfigError("--pos / --neg / --out need a MODEL, not --scores")
        crop_only = [  # options of the crops: a score file has none, they did nothing
            flag
            for flag, used in (
                ("--region", args.region),
                ("--crop-size", args.crop_size),
                ("--strict", args.strict),
            )
            if used
        ]
        if crop_only:
            raise ConfigError(
                f"{', '.join(crop_only)} go(es) with a MODEL's --pos / --neg crops, not with "
                "--scores (a score file has no crops)"
            )
        if not args.json:
            raise ConfigError("--scores needs --json OUT to write the calibration to")
        s, labels = read_scores_csv(args.scores)
        y01, _ = as_binary_labels(
            labels, s.shape[0], name=f"the labels of score file {str(args.scores)!r}"
        )
        source: dict[str, Any] = {"scores": str(args.scores)}
        if bool(((s >= 0) & (s <= 1)).all()):
            before_name, p_before = "before (scores as P)", s
        else:
            before_name, p_before = "before (logistic)", torch.sigmoid(s)
    else:
        if not args.pos or not args.neg:
            raise ConfigError("a MODEL needs labelled calibration crops: --pos DIR and --neg DIR")
        from torchtrack.io.crops import check_crop_folders

        check_crop_folders({"--pos": args.pos, "--neg": args.neg}, "--pos")
        from torchtrack.detect import load_detector, save_detector
        from torchtrack.detect.bundled import resolve_model

        model_file = resolve_model(args.model)  # a file, or a bundled name as elsewhere
        if model_file != Path(args.model) and args.out is None and args.json is None:
            # the package's file stays as shipped: the calibrated copy goes to -o OUT
            raise ConfigError(
                f"MODEL {args.model!r} is a bundled model: give -o OUT for the calibrated "
                "copy (the installed model file is not rewritten) or --json OUT"
            )
        det = load_detector(model_file)
        if (args.region is None) != (args.crop_size is None):
            raise ConfigError("--region and --crop-size go together")
        opts = {
            "strict": args.strict,
            "progress": show_progress(args),
            "region": tuple(args.region) if args.region else None,
            "crop_size": tuple(args.crop_size) if args.crop_size else None,
        }
        m_pos, sk_pos = crop_margins(det, args.pos, **opts)
        m_neg, sk_neg = crop_margins(det, args.neg, **opts)
        s = torch.cat((m_pos, m_neg))
        y01 = torch.cat((torch.ones(len(m_pos)), torch.zeros(len(m_neg)))).long()
        source = {"model": str(args.model), "pos": args.pos, "neg": args.neg}
        if det.calibrator is not None:
            kind = det.calibrator.to_state()[1]["kind"]
            before_name = f"before (model's {kind})"
            p_before = det.calibrator.predict_proba(s)
        else:
            before_name, p_before = "before (logistic)", torch.sigmoid(s)
        source["skipped_files"] = sk_pos + sk_neg

    n_pos, n_neg = int(y01.sum()), int((1 - y01).sum())
    if min(n_pos, n_neg) < args.min_per_class:
        from torchtrack.errors import DataError

        msg = (
            f"{n_pos} positive and {n_neg} negative samples: fewer than --min-per-class "
            f"{args.min_per_class} in a class"
        )
        if not args.force:
            raise DataError(f"too little data to calibrate: {msg} (--force calibrates anyway)")
        print(f"warning (--force): {msg}", file=sys.stderr)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        cal = make_calibrator(args.method).fit(s, y01)
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    data_prior = n_pos / (n_pos + n_neg)
    weights = None
    if args.prior is not None:
        from torchtrack.learn import prior_weights, with_prior

        cal = with_prior(cal, args.prior, data_prior)
        weights = prior_weights(y01, args.prior)
    p_after = cal.predict_proba(s)
    rows = [
        (before_name, calibration_metrics(p_before, y01, args.bins, weights)),
        ("after (in-sample)", calibration_metrics(p_after, y01, args.bins, weights)),
    ]
    p_cv = cv_probabilities(args.method, s, y01, 5, args.seed, args.prior)
    if p_cv is not None:
        rows.append(("after (5-fold CV)", calibration_metrics(p_cv, y01, args.bins, weights)))
    print(f"calibration data: {n_pos + n_neg} scores ({n_pos} positive, {n_neg} negative)")
    print(f"method: {args.method}")
    if args.prior is not None:
        from torchtrack.learn.calibration import prior_shift

        shift = prior_shift(args.prior, data_prior)
        print(
            f"prior: probabilities for a positive share of {args.prior:g} (the calibration "
            f"data's: {data_prior:.4g}), log-odds moved by {shift:+.4g}; the metrics below weight "
            "the samples to that share"
        )
    if args.method == "platt":
        print(f"P(positive | m) = 1 / (1 + exp(A m + B)),  A = {cal.a_:.6g},  B = {cal.b_:.6g}")
    print(_format_table(rows, args.bins))
    if p_cv is None:
        print("(5-fold CV skipped: a class has fewer than 5 samples)")

    metrics = {name: m for name, m in rows}
    record = {
        "method": args.method,
        "n_pos": n_pos,
        "n_neg": n_neg,
        "ece_bins": args.bins,
        "prior": args.prior if args.prior is not None else data_prior,
        "data_prior": data_prior,
        "metrics": metrics,
        "source": source,
    }
    falls = args.method == "platt" and (cal.a_ > 0 or (det is not None and cal.a_ == 0))
    # an isotonic map of one value (the PAV pooled every score: they do not rise with the
    # labels) was written without a word, where Platt's A >= 0 on the same data is refused;
    # identical scores give one value either way (Platt's A = 0, warned, kept for --scores)
    flat = (
        args.method == "isotonic"
        and bool((cal.y_thresholds_ == cal.y_thresholds_[0]).all())
        and (det is not None or not bool((s == s[0]).all()))
    )
    if falls or flat:
        from torchtrack.errors import DataError

        what = "score" if det is None else "model's margin"
        higher = "higher" if falls else "as high as the positives"
        if det is not None:
            why = (
                f"on these crops the model scores the negatives {higher}; are --pos and --neg "
                "swapped, or is it the wrong model?"
            )
        else:
            why = (
                f"in {str(args.scores)!r} the negatives score {higher}; are the labels swapped "
                "(the larger label is the positive class), or does a lower score mean positive "
                "(then negate the scores)?"
            )
        head = (
            f"the Platt fit gives a probability that falls as the {what} rises "
            f"(A = {cal.a_:.4g} >= 0)"
            if falls
            else f"the isotonic fit gives every {what} the probability "
            f"{float(cal.y_thresholds_[0]):.4g}, so it does not rank them"
        )
        raise DataError(f"{head}: {why} Nothing was written")
    # Every output is written before any is reported, the model (which may be MODEL itself)
    # last: when one fails, those this run created before it are removed (a file that was
    # there before the run, now replaced, is left: its old content is gone either way).
    import contextlib

    written: list[str] = []
    out = None
    try:
        if args.plot:
            curves = {before_name: p_before, "after (in-sample)": p_after}
            if p_cv is not None:
                curves["after (5-fold CV)"] = p_cv
            new_file = not os.path.exists(args.plot)
            reliability_diagram(curves, y01, args.plot, n_bins=args.bins, sample_weight=weights)
            written += [args.plot] if new_file else []
        if args.json:
            doc = {"format": JSON_FORMAT, "format_version": JSON_VERSION, **calibrator_to_dict(cal)}
            doc.update(record)
            new_file = not os.path.exists(args.json)
            write_text_atomic(args.json, json.dumps(doc, indent=2, allow_nan=False) + "\n")
            written += [args.json] if new_file else []
        if det is not None and (args.out or not args.json):  # --json alone: MODEL untouched
            out = args.out or args.model
            new = det.with_calibrator(cal)
            new.summary = {**det.summary, "recalibration": record}
            save_detector(out, new)
    except BaseException:
        for path in written:
            with contextlib.suppress(OSError):
                os.remove(path)
        raise
    if args.json:
        print(f"wrote {args.json}")
    if out is not None:
        print(f"wrote calibration into {out}")
    if args.plot:
        print(f"wrote {args.plot}")
    return 0
