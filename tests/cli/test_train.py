import shutil

import pytest

from torchtrack.cli import main
from torchtrack.detect import load_detector


@pytest.fixture(scope="module")
def crops(data_dir, tmp_path_factory):
    src = data_dir / "detection_crops" / "uiuc_car" / "CarData" / "TrainImages"
    root = tmp_path_factory.mktemp("cli_cars")
    for kind in ("pos", "neg"):
        (root / kind).mkdir()
        for i in range(30):
            shutil.copy(src / f"{kind}-{i}.pgm", root / kind / f"{kind}-{i}.pgm")
    (root / "pos" / "broken.pgm").write_bytes(b"P5 garbage")
    cfg = root / "car.toml"
    cfg.write_text(
        'name = "car"\nwindow = [40, 100]\n[data]\npositives = ["pos"]\nnegatives = ["neg"]\n'
        "mirror_negatives = true\n[features]\nstride = 4\n[learn]\nn_features = 5\n"
    )
    return root


def test_train_from_config(crops, tmp_path, capsys):
    out = tmp_path / "car.safetensors"
    assert main(["train", "--config", str(crops / "car.toml"), "-o", str(out), "--quiet"]) == 0
    assert "wrote" in capsys.readouterr().out
    det = load_detector(out)
    assert det.name == "car" and det.calibrator is not None
    assert det.summary["counts"]["skipped_files"] == 1  # broken.pgm, reported not fatal


def test_strict_fails_on_bad_file(crops, tmp_path, capsys):
    out = tmp_path / "car.safetensors"
    code = main(
        ["train", "--config", str(crops / "car.toml"), "-o", str(out), "--strict", "--quiet"]
    )
    assert code == 1
    err = capsys.readouterr().err
    assert "broken.pgm" in err and "strict" in err
    assert not out.exists()


def test_train_from_folders_and_errors(crops, tmp_path, capsys):
    out = tmp_path / "m.safetensors"
    empty = tmp_path / "empty"
    empty.mkdir()
    code = main(
        [
            "train",
            "--pos",
            str(empty),
            "--neg",
            str(crops / "neg"),
            "--window",
            "40",
            "100",
            "-o",
            str(out),
            "--quiet",
        ]
    )
    assert code == 1 and "no usable image" in capsys.readouterr().err
    assert main(["train", "-o", str(out)]) == 1
    assert "--config" in capsys.readouterr().err


def test_help_has_examples(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    assert "examples:" in capsys.readouterr().out
