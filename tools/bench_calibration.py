"""Calibration: our Platt scaling vs scikit-learn's sigmoid calibration on the same scores.

For each detector config (pedestrians, cars) the non-test crops are split by source file
(a crop and its mirror stay together) into 50% classifier training, 25% calibration and 25%
evaluation. Features: the full Haar bank, 40 features selected by AdaBoost on the training part;
classifiers: discrete AdaBoost (40 rounds) and an RBF SVM on those features. On the same
calibration scores we fit

* ours: ``PlattCalibrator`` (Lin-Lin-Weng Newton) and ``IsotonicCalibrator``;
* scikit-learn: ``CalibratedClassifierCV(FrozenEstimator(clf), method="sigmoid")`` (and
  ``"isotonic"``), where ``clf`` is a frozen wrapper whose ``decision_function`` returns the
  precomputed score column,

and report NLL / Brier / ECE (15 equal-width bins) on the evaluation part, max |A - A_sk| and
|B - B_sk|, and the median fit time of each calibrator.

    python tools/bench_calibration.py
    python tools/bench_calibration.py --configs configs/vehicle.toml --max-crops 2000

Writes docs/benchmarks/calibration.md and docs/benchmarks/calibration_reliability.png.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from sklearn.base import BaseEstimator, ClassifierMixin

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchtrack.detect.config import load_train_config  # noqa: E402
from torchtrack.detect.training import group_split, load_training_data  # noqa: E402
from torchtrack.features.haar import haar_bank, haar_features_dense  # noqa: E402
from torchtrack.io.atomic import write_text_atomic  # noqa: E402
from torchtrack.learn import (  # noqa: E402
    BoostedStumps,
    IsotonicCalibrator,
    PlattCalibrator,
    SVMClassifier,
    calibration_metrics,
    reliability_diagram,
    select_features,
)


class ScoreColumn(ClassifierMixin, BaseEstimator):
    """A 'classifier' over precomputed scores: ``decision_function(X) = X[:, 0]``."""

    def fit(self, X, y):
        self.classes_ = np.unique(y)
        return self

    def decision_function(self, X):
        return np.asarray(X, dtype=np.float64)[:, 0]

    def predict(self, X):
        return self.classes_[(self.decision_function(X) > 0).astype(int)]


def _median_time(fn, repeats: int) -> tuple[float, object]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def _scores(cfg_path: str, max_crops: int, seed: int, log):
    cfg = load_train_config(cfg_path)
    g = torch.Generator().manual_seed(seed)
    data = load_training_data(cfg, generator=g)
    crops = torch.cat((data.positives.images, data.negatives.images))
    y = torch.cat((torch.ones(len(data.positives)), torch.zeros(len(data.negatives)))).long()
    sources = data.positives.sources + data.negatives.sources
    if max_crops and max_crops < len(y):
        keep = torch.randperm(len(y), generator=g)[:max_crops].sort().values
        crops, y = crops[keep], y[keep]
        sources = [sources[i] for i in keep.tolist()]
    train, rest = group_split(sources, 0.5, generator=g)
    cal_i, ev_i = group_split([sources[i] for i in rest.tolist()], 0.5, generator=g)
    cal, ev = rest[cal_i], rest[ev_i]
    bank = haar_bank(tuple(cfg.window), n_scales=cfg.features.n_scales, stride=cfg.features.stride)
    Xtr = haar_features_dense(crops[train], bank)
    sel = select_features(Xtr, y[train], 40)
    Xtr = Xtr[:, sel].contiguous()
    Xcal = haar_features_dense(crops[cal], bank)[:, sel]
    Xev = haar_features_dense(crops[ev], bank)[:, sel]
    log(
        f"{cfg.name}: {len(train)} train / {len(cal)} calibration / {len(ev)} evaluation crops, "
        f"F = {len(bank)}"
    )
    out = {}
    for name, clf in (
        ("AdaBoost (discrete, 40)", BoostedStumps(40)),
        ("SVM (RBF)", SVMClassifier(kernel="rbf")),
    ):
        clf.fit(Xtr, y[train])
        s_cal = clf.decision_function(Xcal).double().numpy()
        s_ev = clf.decision_function(Xev).double().numpy()
        out[name] = (s_cal, y[cal].numpy(), s_ev, y[ev].numpy())
    return cfg.name, (len(train), len(cal), len(ev)), out


def _fit_all(s_cal, y_cal, s_ev, repeats):
    """Fit ours and scikit-learn's calibrators on the same calibration scores; return the
    evaluation probabilities with median fit times, and the two fitted sigmoid models."""
    from sklearn.calibration import CalibratedClassifierCV
    from sklearn.frozen import FrozenEstimator

    frozen = FrozenEstimator(ScoreColumn().fit(s_cal[:, None], y_cal))

    def sk_fit(method):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return CalibratedClassifierCV(frozen, method=method).fit(s_cal[:, None], y_cal)

    res = {}
    t, ours = _median_time(lambda: PlattCalibrator().fit(s_cal, y_cal), repeats)
    res["ours Platt"] = (ours.predict_proba(s_ev), t)
    t, sk = _median_time(lambda: sk_fit("sigmoid"), repeats)
    res["sklearn sigmoid"] = (sk.predict_proba(s_ev[:, None])[:, 1], t)
    t, iso = _median_time(lambda: IsotonicCalibrator().fit(s_cal, y_cal), repeats)
    res["ours isotonic"] = (iso.predict_proba(s_ev), t)
    t, ski = _median_time(lambda: sk_fit("isotonic"), repeats)
    res["sklearn isotonic"] = (ski.predict_proba(s_ev[:, None])[:, 1], t)
    res["uncalibrated 1/(1+exp(-m))"] = (1 / (1 + np.exp(-s_ev)), float("nan"))
    return res, ours, sk


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument(
        "--configs",
        nargs="+",
        default=[str(ROOT / "configs" / "pedestrian.toml"), str(ROOT / "configs" / "vehicle.toml")],
    )
    ap.add_argument("--max-crops", type=int, default=0, help="subsample crops (0 = all)")
    ap.add_argument("--repeats", type=int, default=7, help="timing repeats (median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "calibration.md"))
    args = ap.parse_args()
    script = Path(sys.argv[0]).resolve()
    script_s = script.relative_to(ROOT).as_posix() if script.is_relative_to(ROOT) else str(script)
    command = " ".join(["python", script_s, *sys.argv[1:]])
    rows, ab_rows, data_rows = [], [], []
    max_da = max_db = 0.0
    plot_done = False
    for cfg_path in args.configs:
        name, counts, sets = _scores(cfg_path, args.max_crops, args.seed, print)
        data_rows.append(f"| {name} | {counts[0]} | {counts[1]} | {counts[2]} |")
        for clf_name, (s_cal, y_cal, s_ev, y_ev) in sets.items():
            res, ours, sk = _fit_all(s_cal, y_cal, s_ev, args.repeats)
            sk_cal = sk.calibrated_classifiers_[0].calibrators[0]
            da, db = abs(ours.a_ - sk_cal.a_), abs(ours.b_ - sk_cal.b_)
            max_da, max_db = max(max_da, da), max(max_db, db)
            ab_rows.append(
                f"| {name} | {clf_name} | {ours.a_:.6f} | {sk_cal.a_:.6f} | {da:.2e} | "
                f"{ours.b_:.6f} | {sk_cal.b_:.6f} | {db:.2e} |"
            )
            for method, (p, t) in res.items():
                m = calibration_metrics(p, y_ev)
                ts = "" if t != t else f"{t * 1e3:.2f}"
                rows.append(
                    f"| {name} | {clf_name} | {method} | {m['nll']:.4f} | {m['brier']:.4f} | "
                    f"{m['ece']:.4f} | {ts} |"
                )
            print(rows[-5:], flush=True)
            if not plot_done:
                reliability_diagram(
                    {k: v[0] for k, v in res.items() if k != "sklearn isotonic"},
                    y_ev,
                    Path(args.out).with_name("calibration_reliability.png"),
                    title=f"{name}, {clf_name}: evaluation split",
                )
                plot_done = True

    nl = "\n"
    md = f"""# Calibration: ours vs scikit-learn on the same scores

Command: `{command}`

Splits of the non-test crops by source file (the test split is never read): 50% classifier
training, 25% calibration (calibrators are fitted here), 25% evaluation (metrics below).
40 features selected by AdaBoost on the full Haar bank. ECE: 15 equal-width bins.
Fit times: median of {args.repeats} runs, in milliseconds (one shared 2-core machine).

| data | train | calibration | evaluation |
|---|---:|---:|---:|
{nl.join(data_rows)}

## Held-out (evaluation split) metrics

| data | classifier | calibration | NLL | Brier | ECE | fit time (ms) |
|---|---|---|---:|---:|---:|---:|
{nl.join(rows)}

## Fitted sigmoid parameters, P = 1 / (1 + exp(A m + B)) (same sign convention in both)

| data | classifier | A (ours) | A (sklearn) | abs diff | B (ours) | B (sklearn) | abs diff |
|---|---|---:|---:|---:|---:|---:|---:|
{nl.join(ab_rows)}

**max |A - A_sk| = {max_da:.2e}, max |B - B_sk| = {max_db:.2e}** (goal: <= 1e-3).

Reliability diagram of the first data set / classifier: `calibration_reliability.png`.
"""
    write_text_atomic(args.out, md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
