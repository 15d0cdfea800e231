"""``torchtrack calibrate``: CSV and model inputs, outputs, diagnostics and bad input."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main
from torchtrack.learn import (
    BoostedStumps,
    IsotonicCalibrator,
    PlattCalibrator,
    calibrator_from_dict,
    select_features,
)


def _scores(n=200, seed=0):
    rng = np.random.default_rng(seed)
    y = (rng.random(n) < 0.4).astype(int)
    s = rng.normal(size=n) * 1.5 + 2.0 * y
    return s, y


def _write_csv(path, s, y, header=True, label_map=None):
    lines = ["score,label"] if header else []
    for a, b in zip(s, y, strict=True):
        lines.append(f"{float(a)!r},{label_map[b] if label_map else b}")
    path.write_text("\n".join(lines) + "\n")


def test_csv_platt_json_and_plot(tmp_path, capsys):
    s, y = _scores()
    _write_csv(tmp_path / "s.csv", s, y)
    out, png = tmp_path / "cal.json", tmp_path / "rel.png"
    rc = main(
        ["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(out), "--plot", str(png)]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "NLL" in text and "after (5-fold CV)" in text and "A = " in text
    doc = json.loads(out.read_text())
    assert doc["format"] == "torchtrack-calibration" and doc["n_pos"] == int(y.sum())
    cal = calibrator_from_dict(doc)
    ref = PlattCalibrator().fit(s, y)
    assert cal.a_ == pytest.approx(ref.a_, abs=1e-12) and cal.b_ == pytest.approx(ref.b_, abs=1e-12)
    assert png.read_bytes()[:4] == b"\x89PNG"
    after = doc["metrics"]["after (in-sample)"]
    assert after["nll"] < doc["metrics"]["before (logistic)"]["nll"]


def test_csv_no_header_isotonic_pm1_labels(tmp_path):
    s, y = _scores(150, 1)
    _write_csv(tmp_path / "s.csv", s, y, header=False, label_map={0: -1, 1: 1})
    out = tmp_path / "iso.json"
    rc = main(
        [
            "calibrate",
            "--scores",
            str(tmp_path / "s.csv"),
            "--method",
            "isotonic",
            "--json",
            str(out),
        ]
    )
    assert rc == 0
    cal = calibrator_from_dict(json.loads(out.read_text()))
    ref = IsotonicCalibrator().fit(s, y)
    grid = np.linspace(-5, 6, 101)
    np.testing.assert_array_equal(cal.predict_proba(grid), ref.predict_proba(grid))


def test_csv_header_with_named_columns_in_other_order(tmp_path):
    s, y = _scores(60, 2)
    lines = ["id,label,score"] + [
        f"{i},{b},{float(a)!r}" for i, (a, b) in enumerate(zip(s, y, strict=True))
    ]
    (tmp_path / "s.csv").write_text("\n".join(lines))
    out = tmp_path / "c.json"
    assert main(["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(out)]) == 0
    assert calibrator_from_dict(json.loads(out.read_text())).a_ == pytest.approx(
        PlattCalibrator().fit(s, y).a_, abs=1e-12
    )


def test_csv_bad_rows_reported_by_line(tmp_path, capsys):
    (tmp_path / "s.csv").write_text("score,label\n0.5,1\nabc,0\n0.1\n\n0.3,0\nnan,1\n")
    rc = main(
        ["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(tmp_path / "o.json")]
    )
    assert rc == 1
    err = capsys.readouterr().err
    assert "3 bad row(s)" in err and "line 3" in err and "line 4" in err and "line 7" in err
    assert not (tmp_path / "o.json").exists()


def test_csv_first_row_half_numbers_is_not_a_header(tmp_path, capsys):
    """A first data row with a typo ('0.9O,1': one number, one word) was taken as a header
    and dropped without a word; a header has no number in its first two cells."""
    s, y = _scores(40)
    for first, what in (("0.9O,1", "column 2 '1' is a number"), ("1,lab", "column 1 '1'")):
        _write_csv(tmp_path / "s.csv", s, y, header=False)
        text = (tmp_path / "s.csv").read_text()
        (tmp_path / "s.csv").write_text(f"{first}\n{text}")
        out = tmp_path / "o.json"
        assert main(["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(out)]) == 1
        err = capsys.readouterr().err
        assert f"s.csv' line 1: '{first}' is neither a header (its {what}" in err, err
        assert not out.exists()


def test_csv_single_class_and_identical_scores(tmp_path, capsys):
    (tmp_path / "one.csv").write_text("1.0,1\n2.0,1\n0.5,1\n")
    assert (
        main(
            ["calibrate", "--scores", str(tmp_path / "one.csv"), "--json", str(tmp_path / "o.json")]
        )
        == 1
    )
    err = capsys.readouterr().err
    assert "exactly two classes" in err and "one.csv" in err  # the file is named
    (tmp_path / "same.csv").write_text("".join(f"0.7,{i % 2}\n" for i in range(20)))
    assert (
        main(
            [
                "calibrate",
                "--scores",
                str(tmp_path / "same.csv"),
                "--json",
                str(tmp_path / "o.json"),
            ]
        )
        == 0
    )
    assert "identical" in capsys.readouterr().err


def test_argument_errors(tmp_path, capsys):
    (tmp_path / "s.csv").write_text("0.1,0\n0.9,1\n")
    assert main(["calibrate", "--scores", str(tmp_path / "s.csv")]) == 1
    assert "--json" in capsys.readouterr().err
    assert main(["calibrate", "m.safetensors", "--scores", str(tmp_path / "s.csv")]) == 1
    assert "not both" in capsys.readouterr().err
    assert (
        main(["calibrate", str(tmp_path / "missing.safetensors"), "--pos", "a", "--neg", "b"]) == 1
    )
    assert "does not exist" in capsys.readouterr().err
    assert main(["calibrate", "--scores", str(tmp_path / "nope.csv"), "--json", "o.json"]) == 1
    assert "cannot read" in capsys.readouterr().err


# ------------------------------------------------------------------------- model input


def _blob_crops(n, positive, rng, size=16):
    imgs = rng.integers(60, 140, size=(n, size, size)).astype(np.float64)
    if positive:  # a bright vertical bar in the middle: easy but noisy class
        imgs[:, 2:-2, size // 2 - 2 : size // 2 + 2] += rng.uniform(10, 80, size=(n, 1, 1))
    return np.clip(imgs, 0, 255).astype(np.uint8)


@pytest.fixture
def tiny_model(tmp_path):
    from torchtrack.detect import Detector, save_detector
    from torchtrack.features.haar import haar_bank, haar_features_dense

    rng = np.random.default_rng(0)
    bank = haar_bank((16, 16), sizes=(8, 4), stride=2)
    pos, neg = _blob_crops(60, True, rng), _blob_crops(60, False, rng)
    crops = torch.from_numpy(np.concatenate([pos, neg]))[:, None]
    y = torch.cat((torch.ones(60), torch.zeros(60))).long()
    X = haar_features_dense(crops, bank)
    idx = select_features(X, y, 5)
    clf = BoostedStumps(10).fit(X[:, idx], y)
    det = Detector(bank, idx, clf, None, name="bar")
    path = tmp_path / "bar.safetensors"
    save_detector(path, det)
    for name, arr in (("pos", _blob_crops(40, True, rng)), ("neg", _blob_crops(50, False, rng))):
        d = tmp_path / name
        d.mkdir()
        for i, im in enumerate(arr):
            cv2.imwrite(str(d / f"{i:03d}.png"), im)
    return path


def test_model_in_place_and_json(tiny_model, tmp_path, capsys):
    from torchtrack.detect import load_detector

    before = tiny_model.read_bytes()
    js = tmp_path / "c.json"
    args = [
        "calibrate",
        str(tiny_model),
        "--pos",
        str(tmp_path / "pos"),
        "--neg",
        str(tmp_path / "neg"),
    ]
    assert main([*args, "--json", str(js), "--quiet"]) == 0
    assert tiny_model.read_bytes() == before  # --json leaves the model alone
    assert "before (logistic)" in capsys.readouterr().out
    assert main([*args, "--quiet", "--plot", str(tmp_path / "r.png")]) == 0
    det = load_detector(tiny_model)
    assert isinstance(det.calibrator, PlattCalibrator)
    assert det.summary["recalibration"]["n_pos"] == 40
    # the stored calibration is the Platt fit of the detector's margins on those crops
    from torchtrack.io.crops import load_crops

    margins = []
    for name in ("pos", "neg"):
        imgs = load_crops(tmp_path / name, det.window).images
        boxes = torch.tensor([0.0, 0.0, 16.0, 16.0]).expand(imgs.shape[0], 1, 4)
        margins.append(det.decision_function(imgs, boxes)[:, 0].double())
    ref = PlattCalibrator().fit(torch.cat(margins), torch.cat((torch.ones(40), torch.zeros(50))))
    assert det.calibrator.a_ == pytest.approx(ref.a_, abs=1e-9)
    assert calibrator_from_dict(json.loads(js.read_text())).b_ == pytest.approx(ref.b_, abs=1e-9)
    # a second run reports the model's current calibration as "before"; -o writes a copy
    out2 = tmp_path / "iso.safetensors"
    assert main([*args, "--quiet", "--method", "isotonic", "-o", str(out2)]) == 0
    assert "before (model's platt)" in capsys.readouterr().out
    assert isinstance(load_detector(out2).calibrator, IsotonicCalibrator)
    assert isinstance(load_detector(tiny_model).calibrator, PlattCalibrator)


def test_a_failing_output_takes_the_others_of_the_run_with_it(
    tiny_model, tmp_path, capsys, monkeypatch
):
    """-o OUT with --json writes both; when the model, written last, fails, the plot and the
    JSON of that run are removed (they were left behind; -o with --json wrote no model)."""
    import torchtrack.detect
    from torchtrack.errors import ConfigError

    args = ["calibrate", str(tiny_model), "--pos", str(tmp_path / "pos"), "--neg"]
    args += [str(tmp_path / "neg"), "--quiet", "--plot", str(tmp_path / "r.png")]
    args += ["--json", str(tmp_path / "c.json"), "-o", str(tmp_path / "m.safetensors")]

    def full(path, det):
        raise ConfigError(f"cannot write {str(path)!r}: No space left on device")

    monkeypatch.setattr(torchtrack.detect, "save_detector", full)
    assert main(args) == 1
    monkeypatch.undo()
    assert "No space left" in capsys.readouterr().err
    assert not any((tmp_path / f).exists() for f in ("r.png", "c.json", "m.safetensors"))
    assert main(args) == 0
    assert all((tmp_path / f).is_file() for f in ("r.png", "c.json", "m.safetensors"))


def test_model_bad_crop_folder(tiny_model, tmp_path, capsys):
    (tmp_path / "neg" / "notes.bin").write_bytes(b"not an image")
    args = [
        "calibrate",
        str(tiny_model),
        "--pos",
        str(tmp_path / "pos"),
        "--neg",
        str(tmp_path / "neg"),
    ]
    assert main([*args, "--quiet", "--json", str(tmp_path / "c.json")]) == 0
    assert "notes.bin" in capsys.readouterr().err
    assert main([*args, "--quiet", "--strict", "--json", str(tmp_path / "c.json")]) == 1
    assert "notes.bin" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert (
        main(
            [
                "calibrate",
                str(tiny_model),
                "--pos",
                str(tmp_path / "empty"),
                "--neg",
                str(tmp_path / "neg"),
                "--quiet",
            ]
        )
        == 1
    )
    assert "no usable image" in capsys.readouterr().err
    assert main(["calibrate", str(tiny_model), "--pos", str(tmp_path / "pos")]) == 1
    assert "--neg" in capsys.readouterr().err


def test_model_region_crops(tiny_model, tmp_path):
    rng = np.random.default_rng(5)
    for name in ("pos", "neg"):
        d = tmp_path / f"{name}_pad"
        d.mkdir()
        for f in sorted((tmp_path / name).iterdir()):
            im = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            big = rng.integers(0, 255, size=(20, 20)).astype(np.uint8)
            big[2:18, 2:18] = im
            cv2.imwrite(str(d / f.name), big)
    plain, padded = tmp_path / "plain.json", tmp_path / "padded.json"
    base = ["calibrate", str(tiny_model), "--quiet"]
    assert (
        main(
            [
                *base,
                "--pos",
                str(tmp_path / "pos"),
                "--neg",
                str(tmp_path / "neg"),
                "--json",
                str(plain),
            ]
        )
        == 0
    )
    pad = ["--pos", str(tmp_path / "pos_pad"), "--neg", str(tmp_path / "neg_pad")]
    assert (
        main(
            [
                *base,
                *pad,
                "--crop-size",
                "20",
                "20",
                "--region",
                "2",
                "2",
                "16",
                "16",
                "--json",
                str(padded),
            ]
        )
        == 0
    )
    a = calibrator_from_dict(json.loads(plain.read_text())).a_
    assert calibrator_from_dict(json.loads(padded.read_text())).a_ == pytest.approx(a, abs=1e-9)
    assert main([*base, *pad, "--region", "2", "2", "16", "16", "--json", str(padded)]) == 1


def test_bundled_model_by_name_needs_an_output(data_dir, tmp_path, capsys):
    """``calibrate pedestrian`` takes the bundled name like the other subcommands, writes the
    calibrated copy to -o, and never rewrites the installed model file."""
    import hashlib

    from torchtrack.detect import load_detector
    from torchtrack.detect.bundled import resolve_model

    crops = data_dir / "detection_crops"
    pos, neg = tmp_path / "pos", tmp_path / "neg"
    for folder, src, n in (
        (pos, crops / "inria_person_96x160" / "pos", 15),
        (neg, crops / "inria_negatives" / "test", 12),
    ):
        folder.mkdir()
        for f in sorted(src.iterdir())[:n]:
            (folder / f.name).symlink_to(f)
    installed = resolve_model("pedestrian")
    digest = hashlib.sha256(installed.read_bytes()).hexdigest()
    args = ["calibrate", "pedestrian", "--pos", str(pos), "--neg", str(neg), "--quiet"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "'pedestrian' is a bundled model" in err and "-o OUT" in err
    out = tmp_path / "ped.safetensors"
    assert main([*args, "-o", str(out)]) == 0
    det = load_detector(out)
    assert det.summary["recalibration"]["n_pos"] == 15
    assert det.summary["recalibration"]["n_neg"] == 12
    assert det.calibrator.a_ < 0
    assert hashlib.sha256(installed.read_bytes()).hexdigest() == digest


def test_help_examples_keep_their_line_breaks(capsys):
    # A lone backslash at the end of an epilog line joined the INRIA example's two lines into
    # one with a run of spaces in the middle; every example is written as shown, `\` included.
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = capsys.readouterr().out
    assert "--neg calib/background \\\n      --crop-size 160 96 --region 16 16 64 128" in text
    assert "background       --crop-size" not in text


def test_prior_moves_the_fit_to_another_share_of_positives(tmp_path, capsys):
    """--prior P: the Platt fit's log-odds move by logit(P) - logit(the data's share), the
    metrics are weighted to P, the JSON records both shares; a bad share writes nothing."""
    s, y = _scores(400, 4)
    _write_csv(tmp_path / "s.csv", s, y)
    plain, moved = tmp_path / "plain.json", tmp_path / "moved.json"
    assert main(["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(plain)]) == 0
    capsys.readouterr()
    args = ["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(moved)]
    assert main([*args, "--prior", "0.02", "--plot", str(tmp_path / "r.png")]) == 0
    text = capsys.readouterr().out
    share = y.mean()
    shift = np.log(0.02 / 0.98) - np.log(share / (1 - share))
    assert f"(the calibration data's: {share:.4g}), log-odds moved by {shift:+.4g}" in text
    a, b = json.loads(plain.read_text()), json.loads(moved.read_text())
    assert b["prior"] == 0.02 and b["data_prior"] == pytest.approx(share) == a["prior"]
    ca, cb = calibrator_from_dict(a), calibrator_from_dict(b)
    assert cb.a_ == ca.a_ and cb.b_ == pytest.approx(ca.b_ - shift, abs=1e-9)
    # the in-sample ECE of the moved fit, weighted to 2%, is the one of data at that share
    from torchtrack.learn import calibration_metrics, prior_weights

    w = prior_weights(y, 0.02)
    ece = calibration_metrics(cb.predict_proba(s), y, 15, w)["ece"]
    assert b["metrics"]["after (in-sample)"]["ece"] == pytest.approx(ece, abs=1e-12)
    assert b["metrics"]["after (in-sample)"] != a["metrics"]["after (in-sample)"]
    for bad in ("0", "1", "1.5", "-0.1", "nan"):
        out = tmp_path / f"bad{bad}.json"
        rc = main(
            ["calibrate", "--scores", str(tmp_path / "s.csv"), "--json", str(out), "--prior", bad]
        )
        assert rc == 1 and not out.exists()
        assert "--prior must be a share of positives in (0, 1)" in capsys.readouterr().err


def test_prior_with_a_model(tiny_model, tmp_path, capsys):
    from torchtrack.detect import load_detector

    args = ["calibrate", str(tiny_model), "--pos", str(tmp_path / "pos"), "--neg",
            str(tmp_path / "neg"), "--quiet"]  # fmt: skip
    plain, moved = tmp_path / "plain.safetensors", tmp_path / "moved.safetensors"
    assert main([*args, "-o", str(plain)]) == 0
    assert main([*args, "-o", str(moved), "--prior", "0.1"]) == 0
    a, b = load_detector(plain), load_detector(moved)
    shift = np.log(0.1 / 0.9) - np.log(40 / 50)  # 40 positive and 50 negative crops
    assert b.calibrator.b_ == pytest.approx(a.calibrator.b_ - shift, abs=1e-9)
    assert b.summary["recalibration"]["prior"] == 0.1
    assert b.summary["recalibration"]["data_prior"] == pytest.approx(40 / 90)
