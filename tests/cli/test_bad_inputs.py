"""The bad-input corpus (issue 12): every subcommand fed what a hostile but realistic user would
give it, in process (``torchtrack.cli.main``) on tiny generated inputs.

Each case asserts the exit code, the error message (or, for inputs rightly accepted, the
output), that no Python traceback escapes, and that a failed run leaves no output file in its
output folder. ``{c}`` in an argument is the corpus folder, ``{o}`` the case's own (empty)
output folder.
"""

from __future__ import annotations

import json
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchtrack.cli import main


@dataclass(frozen=True)
class Case:
    """One command line: ``code`` the expected exit status, ``match`` a regex the command's
    stderr (errors) or stdout + stderr (accepted runs) must contain, ``keep`` the files the
    run must leave in ``{o}`` (empty for failures: nothing may be left)."""

    id: str
    argv: tuple[str, ...]
    code: int
    match: str
    keep: tuple[str, ...] = field(default_factory=tuple)


def E(id: str, argv: str, match: str, code: int = 1) -> Case:
    """A case that must fail cleanly."""
    return Case(id, tuple(_split(argv)), code, match)


def A(id: str, argv: str, match: str, keep: tuple[str, ...] = ()) -> Case:
    """A case that must be accepted (exit 0) and leave exactly ``keep`` in ``{o}``."""
    return Case(id, tuple(_split(argv)), 0, match, keep)


def _split(argv: str) -> list[str]:
    import shlex

    return shlex.split(argv)


# --------------------------------------------------------------------------- the corpus
def _toy_detector(window=(16, 8), svm=False):
    from torchtrack.detect import Detector
    from torchtrack.features.haar import haar_bank
    from torchtrack.learn import BoostedStumps, PlattCalibrator, SVMClassifier

    g = torch.Generator().manual_seed(0)
    x = torch.randn(80, 4, generator=g)
    y = (x[:, 0] - x[:, 2] + 0.5 * torch.randn(80, generator=g) > 0).long()
    clf = (SVMClassifier() if svm else BoostedStumps(n_estimators=5)).fit(x, y)
    cal = PlattCalibrator().fit(clf.decision_function(x).double(), y)
    bank = haar_bank(window, sizes=(8, 4))
    return Detector(bank, torch.tensor([3, 50, 200, 360]), clf, cal, name="toy")


def _frames(folder: Path, n=6, size=(48, 64), ext=".png"):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(0)
    bg = cv2.GaussianBlur(rng.integers(0, 255, (*size, 3), np.uint8), (7, 7), 3)
    for t in range(n):
        f = bg.copy()
        f[14:34, 10 + 2 * t : 24 + 2 * t] = (30, 30, 220)
        assert cv2.imwrite(str(folder / f"{t:04d}{ext}"), f)
    return folder


def _video(path: Path, n=10, size=(48, 64), fourcc="mp4v"):
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10.0, (size[1], size[0]))
    rng = np.random.default_rng(1)
    for t in range(n):
        f = cv2.GaussianBlur(rng.integers(0, 255, (*size, 3), np.uint8), (5, 5), 2)
        f[14:34, 10 + 2 * t : 24 + 2 * t] = (30, 30, 220)
        w.write(f)
    w.release()
    return path


def _crops(folder: Path, n: int, kind: str, size=(16, 16), seed=0):
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        if kind == "pos":  # a bright bar on noise
            img = rng.integers(0, 60, size, np.uint8)
            img[:, size[1] // 3 : 2 * size[1] // 3] = 220
        elif kind == "flat":
            img = np.full(size, 128, np.uint8)
        else:
            img = rng.integers(0, 255, size, np.uint8)
        cv2.imwrite(str(folder / f"{kind}{i:03d}.png"), img)
    return folder


def _otb(folder: Path, n=6, gt: str | None = None):
    _frames(folder / "img", n, ext=".jpg")
    rows = gt if gt is not None else "".join(f"{11 + 2 * t},15,14,20\n" for t in range(n))
    (folder / "groundtruth_rect.txt").write_text(rows)
    return folder


@pytest.fixture(scope="module")
def corpus(tmp_path_factory, forge_model):
    from torchtrack.detect import save_detector
    from torchtrack.detect.signing import generate_key

    c = tmp_path_factory.mktemp("corpus")
    # frames and videos
    _frames(c / "frames")
    _frames(c / "jpgs", ext=".jpg")
    data = (c / "jpgs" / "0002.jpg").read_bytes()
    (c / "jpgs" / "0002.jpg").write_bytes(data[: len(data) // 4])  # truncated
    (c / "corrupt").mkdir()
    for i in range(3):
        (c / "corrupt" / f"{i}.jpg").write_bytes(b"not a jpeg at all " * 3)
    (c / "tiny").mkdir()
    for i in range(3):
        cv2.imwrite(str(c / "tiny" / f"{i}.png"), np.zeros((1, 1, 3), np.uint8))
    (c / "emptydir").mkdir()
    # links to the frames, the third one broken (its target gone)
    (c / "linked").mkdir()
    for f in sorted((c / "frames").iterdir()):
        (c / "linked" / f.name).symlink_to(f if f.name != "0002.png" else c / "gone.png")
    (c / "notes").mkdir()
    (c / "notes" / "readme.txt").write_text("no images here")
    _frames(c / "motseq" / "img1", 3, ext=".jpg")  # a MOTChallenge sequence's folder
    (c / "motseq" / "seqinfo.ini").write_text("[Sequence]\nname=motseq\nimDir=img1\n")
    _video(c / "clip.mp4")
    v = (c / "clip.mp4").read_bytes()
    (c / "cut.mp4").write_bytes(v[: len(v) // 2])  # no moov atom: cannot be opened
    _video(c / "clip.avi", fourcc="MJPG")
    v = (c / "clip.avi").read_bytes()
    (c / "cut.avi").write_bytes(v[: len(v) // 2])  # frames readable, then it ends early
    (c / "empty.mp4").write_bytes(b"")
    # a header and no frame: it opens, then gives nothing (the messages ended in '()')
    cv2.VideoWriter(str(c / "zero.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48)).release()
    (c / "text.mp4").write_text("this is not a video\n")
    (c / "photo.png").write_bytes((c / "frames" / "0000.png").read_bytes())
    _frames(c / "samestem", 3)  # 0000.png ... 0002.png, and a 0001.jpg beside them
    cv2.imwrite(str(c / "samestem" / "0001.jpg"), cv2.imread(str(c / "frames" / "0001.png")))
    (c / "afile").write_text("x")
    # models
    toy = save_detector(c / "toy.safetensors", _toy_detector())
    save_detector(c / "svm.safetensors", _toy_detector(svm=True))
    raw = _toy_detector()
    raw.calibrator = None
    save_detector(c / "uncal.safetensors", raw)
    b = toy.read_bytes()
    (c / "trunc.safetensors").write_bytes(b[: len(b) - 7])
    (c / "trail.safetensors").write_bytes(b + b"\0" * 8)
    (c / "junk.safetensors").write_bytes(b"\x07" * 40)
    (c / "tiny.safetensors").write_bytes(b"\1\2")
    flipped = bytearray(b)
    flipped[-3] ^= 0x10
    (c / "bitflip.safetensors").write_bytes(bytes(flipped))
    priv, _, _ = generate_key(c / "alice.pem")
    generate_key(c / "mallory.pem")
    save_detector(c / "signed.safetensors", _toy_detector(), signing_key=priv)
    (c / "junk.pub").write_text("-----BEGIN PUBLIC KEY-----\nnope\n-----END PUBLIC KEY-----\n")
    for name, kw in FORGERIES.items():
        forge_model(toy, c / f"forged_{name}.safetensors", **kw)
    forge_model(
        c / "signed.safetensors",
        c / "forged_signed.safetensors",
        meta_edit=lambda m: m["calibration"].update(b=m["calibration"]["b"] - 0.5),
    )
    # crops
    _crops(c / "crops" / "pos", 40, "pos")
    _crops(c / "crops" / "neg", 40, "neg", seed=1)
    _crops(c / "few" / "pos", 3, "pos")
    _crops(c / "few" / "neg", 3, "neg", seed=1)
    _crops(c / "flat" / "pos", 40, "flat")
    (c / "badcrops").mkdir()
    for i in range(4):
        (c / "badcrops" / f"{i}.png").write_bytes(b"\x89PNG broken")
    (c / "split.txt").write_text("pos000.png\n")
    (c / "bad.toml").write_text("window = [16, 16\n")
    (c / "unknown.toml").write_text(
        'window = [16, 16]\nsurprise = 1\n[data]\npositives = ["crops/pos"]\n'
    )
    (c / "tracker_unknown.toml").write_text("n_particles = 50\nsurprise = 2\n")
    # nested 10^5 deep: the TOML and JSON decoders' RecursionError was a traceback
    (c / "deep.toml").write_text("a = " + "[" * 100_000 + "]" * 100_000 + "\n")
    (c / "deep.json").write_text('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    (c / "haar_stride.toml").write_text(  # a bank no model file holds: trained, then refused
        'window = [16, 16]\n[data]\npositives = ["crops/pos"]\nnegatives = ["crops/neg"]\n'
        '[features]\nkind = "haar"\nstride = 17\n[learn]\nn_features = 4\n'
    )
    # scores
    rng = np.random.default_rng(2)
    m = rng.normal(size=200)
    y = (m + rng.normal(size=200) > 0).astype(int)
    (c / "scores.csv").write_text(
        "score,label\n" + "".join(f"{a},{b}\n" for a, b in zip(m, y, strict=True))
    )
    (c / "scores3.csv").write_text("0.1,0\n0.9,1\n0.5,1\n")
    (c / "onelabel.csv").write_text("".join(f"{a},1\n" for a in m[:50]))
    (c / "nan.csv").write_text("0.1,0\nnan,1\n0.3,1\n")
    (c / "text.csv").write_text("0.1,0\nabc,1\n")
    (c / "header.csv").write_text("score,label\n")
    (c / "empty.csv").write_text("")
    (c / "threelabels.csv").write_text("".join(f"{a},{i % 3}\n" for i, a in enumerate(m)))
    (c / "latin1.csv").write_bytes("0.1,0\n0.2,1 \xe9\n".encode("latin-1"))
    (c / "cols.csv").write_text("0.1\n0.2\n")
    (c / "inverted.csv").write_text(  # the labels flipped: P falls as the score rises
        "score,label\n" + "".join(f"{a},{1 - b}\n" for a, b in zip(m, y, strict=True))
    )
    (c / "huge.csv").write_text(  # the same ranking at magnitudes whose squares overflow
        "score,label\n" + "".join(f"{float(a) * 1e300!r},{b}\n" for a, b in zip(m, y, strict=True))
    )
    (c / "tiny.csv").write_text(  # the same ranking at magnitudes whose squares underflow
        "score,label\n" + "".join(f"{float(a) * 1e-300!r},{b}\n" for a, b in zip(m, y, strict=True))
    )
    # headers naming one of score / label: the first two columns were read by position, so
    # 'frame,score,y' took the frame numbers as the scores
    (c / "nolabel.csv").write_text(
        "frame,score,y\n"
        + "".join(f"{i},{a},{b}\n" for i, (a, b) in enumerate(zip(m, y, strict=True)))
    )
    (c / "noscore.csv").write_text(
        "label,margin\n" + "".join(f"{b},{a}\n" for a, b in zip(m, y, strict=True))
    )
    (c / "labelonly.csv").write_text(  # the named column where the first two put it: read so
        "margin,label\n" + "".join(f"{a},{b}\n" for a, b in zip(m, y, strict=True))
    )
    flat = {"x": [0.1, 0.9], "y": [0.5, 0.5]}  # an isotonic map of one value: no ranking
    (c / "cal_iso_flat.json").write_text(
        json.dumps(
            {
                "format": "torchtrack-calibration",
                "format_version": 1,
                "tensors": {k: {"dtype": "float64", "data": v} for k, v in flat.items()},
                "calibrator": {"kind": "isotonic"},
            }
        )
    )
    (c / "binary.toml").write_bytes(b"\xff\xfe\x00")  # not UTF-8: no TOML, JSON or name list
    for name, a in (("cal_inverted", 1.43), ("cal_flat", 0.0), ("cal_good", -1.2)):
        doc = {"format": "torchtrack-calibration", "format_version": 1, "tensors": {}}
        (c / f"{name}.json").write_text(
            json.dumps({**doc, "calibrator": {"kind": "platt", "a": a, "b": 0.3}})
        )
    # JSON that the json module refuses with a ValueError (not a JSONDecodeError) and a
    # RecursionError: both escaped as tracebacks
    (c / "cal_bigint.json").write_text(
        '{"calibrator": {"kind": "platt", "a": -' + "1" * 5000 + ', "b": 0}}'
    )
    (c / "cal_deep.json").write_text("[" * 100_000 + "]" * 100_000)
    # sequences
    _otb(c / "seqs" / "good")
    _otb(c / "badgt" / "short", gt="11,15,14,20\n13,15,14,20\n")
    _otb(c / "textgt" / "t", gt="11,15,14,20\nfoo,bar\n" + "11,15,14,20\n" * 4)
    (c / "noseq").mkdir()
    (c / "noseq" / "x.txt").write_text("nothing")
    # MOTChallenge: a sequence folder, detections and results
    mot = c / "mot" / "TOY-01"
    _frames(mot / "img1", ext=".jpg")
    (mot / "gt").mkdir()
    (mot / "gt" / "gt.txt").write_text(
        "".join(f"{t + 1},1,{11 + 2 * t},15,14,20,1,-1,-1,-1\n" for t in range(6))
    )
    (mot / "seqinfo.ini").write_text(
        "[Sequence]\nname=TOY-01\nimDir=img1\nframeRate=10\nseqLength=6\nimWidth=64\n"
        "imHeight=48\nimExt=.jpg\n"
    )
    (c / "det.txt").write_text(
        "".join(f"{t + 1},-1,{11 + 2 * t},15,14,20,0.9,-1,-1,-1\n" for t in range(6))
    )
    (c / "det.txt.part").write_text((c / "det.txt").read_text())  # detections, oddly named
    (c / "det_bad.txt").write_text("1,-1,10,15,14,20,0.9,-1,-1,-1\n2,-1,ten,15,14,20,0.9\n")
    (c / "det_zero.txt").write_text("1,-1,10,15,0,20,0.9,-1,-1,-1\n")
    (c / "det_tall.txt").write_text(  # boxes far taller than the frames (wrong units)
        "".join(f"{t + 1},-1,{11 + 2 * t},15,14,20000,0.9,-1,-1,-1\n" for t in range(6))
    )
    (c / "det_twice.txt").write_text(  # every row twice: one person, one target
        "".join(2 * f"{t + 1},-1,{11 + 2 * t},15,14,20,0.9,-1,-1,-1\n" for t in range(6))
    )
    (c / "res.txt").write_text(
        "".join(f"{t + 1},1,{11 + 2 * t},15,14,20,1,-1,-1,-1\n" for t in range(6))
    )
    (c / "res_bad.txt").write_text("1,1,10,15,14,20,1,-1,-1,-1\n1,1,12,15,14,20,1,-1,-1,-1\n")
    (c / "res_hugeid.txt").write_text("1,10000000000000000000,10,15,14,20,1,-1,-1,-1\n")
    # seqinfo.ini variants of the toy sequence (ground truth only: no frames needed to score)
    ini = (mot / "seqinfo.ini").read_text()
    for name, text in (
        ("ESCAPE", ini.replace("name=TOY-01", "name=../escape")),
        ("PCT", ini.replace("name=TOY-01", "name=a%b")),
        ("LONG", ini.replace("seqLength=6", "seqLength=1000000000000")),
    ):
        (c / "mot" / name / "gt").mkdir(parents=True)
        (c / "mot" / name / "gt" / "gt.txt").write_text((mot / "gt" / "gt.txt").read_text())
        (c / "mot" / name / "seqinfo.ini").write_text(text)
    for name, text in (
        ("NOHEADER", ini.replace("[Sequence]\n", "")),  # configparser's message: three lines
        ("GARBAGE", ini.replace("frameRate=10", "frameRate 10\n  [")),
    ):
        (c / "mot" / name / "gt").mkdir(parents=True)
        (c / "mot" / name / "gt" / "gt.txt").write_text((mot / "gt" / "gt.txt").read_text())
        (c / "mot" / name / "seqinfo.ini").write_text(text)
    (c / "mot" / "HALF" / "gt").mkdir(parents=True)  # conf 0.5: a 0/1 flag truncated to 0
    (c / "mot" / "HALF" / "gt" / "gt.txt").write_text(
        (mot / "gt" / "gt.txt").read_text().replace(",1,-1,-1,-1", ",0.5,-1,-1,-1")
    )
    (c / "mot" / "HALF" / "seqinfo.ini").write_text(ini)
    (c / "mot" / "BIN" / "gt").mkdir(parents=True)
    (c / "mot" / "BIN" / "gt" / "gt.txt").write_text((mot / "gt" / "gt.txt").read_text())
    (c / "mot" / "BIN" / "seqinfo.ini").write_bytes(b"\xb3\xff\x00[Sequence]")
    os.mkfifo(c / "pipe")  # an output there would replace the pipe with a plain file
    # two sequences, the second with a frame of another size: it fails after the first was
    # tracked and its tracks written
    import shutil

    shutil.copytree(mot, c / "mot2" / "TOY-01")
    shutil.copytree(mot, c / "mot2" / "TOY-02")
    (c / "mot2" / "TOY-02" / "seqinfo.ini").write_text(ini.replace("name=TOY-01", "name=TOY-02"))
    # frames resized to a tenth of seqinfo.ini's imWidth x imHeight (the ground truth's pixels)
    shutil.copytree(mot, c / "mot" / "RESIZED")
    (c / "mot" / "RESIZED" / "seqinfo.ini").write_text(
        ini.replace("imWidth=64", "imWidth=640").replace("imHeight=48", "imHeight=480")
    )
    # seqinfo.ini's numbers and imExt (the ninth sweep): frameRate=inf was taken, seqLength=6.0
    # was 'not a number', imExt=.png over .jpg frames was ignored
    for name, text in (
        ("RATEINF", ini.replace("frameRate=10", "frameRate=inf")),
        ("LENFLOAT", ini.replace("seqLength=6", "seqLength=6.0")),
    ):
        (c / "mot" / name / "gt").mkdir(parents=True)
        (c / "mot" / name / "gt" / "gt.txt").write_text((mot / "gt" / "gt.txt").read_text())
        (c / "mot" / name / "seqinfo.ini").write_text(text)
    shutil.copytree(mot, c / "mot" / "PNGEXT")
    (c / "mot" / "PNGEXT" / "seqinfo.ini").write_text(ini.replace("imExt=.jpg", "imExt=.png"))
    odd = sorted((c / "mot2" / "TOY-02" / "img1").iterdir())[3]
    cv2.imwrite(str(odd), np.zeros((40, 64, 3), np.uint8))
    return c


FORGERIES = {
    "window": {"meta_edit": lambda m: m.update(window=[100000, 100000])},
    "bankwin": {
        "meta_edit": lambda m: (
            m.update(window=[100000, 100000]),
            m["features"].update(window=[100000, 100000]),
        )
    },
    "platt_sign": {"meta_edit": lambda m: m["calibration"].update(a=-m["calibration"]["a"])},
    "platt_huge": {"meta_edit": lambda m: m["calibration"].update(b=1e308)},
    "threshold": {
        "tensor_edit": lambda t: t.update(
            {"classifier.threshold": t["classifier.threshold"] + 1000}
        )
    },
    "index": {"tensor_edit": lambda t: t.update({"features.index": t["features.index"] + 10**6})},
    "nan": {
        "tensor_edit": lambda t: t.update(
            {"classifier.left": torch.full_like(t["classifier.left"], float("nan"))}
        )
    },
    "meta_list": {"meta_replace": lambda m: [m]},
    "no_offsets": {"header_edit": lambda h: h["features.index"].pop("data_offsets")},
    "str_entry": {"header_edit": lambda h: h.update({"features.index": "oops"})},
    "kind": {"meta_edit": lambda m: m["classifier"].update(kind="forest")},
    "version": {"meta_edit": lambda m: m.update(format_version=99)},
    "nochecksum": {"meta_edit": lambda m: m["training"].update(x=1), "recompute": False},
    "sel": {"meta_edit": lambda m: m["selected_features"].pop()},
    "objbox": {"meta_edit": lambda m: m.update(object_box=[0.9, 0.9, 0.5, 0.5])},
    "name": {"meta_edit": lambda m: m.update(name=7)},
}

FORGED_MSG = {
    "window": "window height",
    "bankwin": "window height",
    "platt_sign": "Platt slope",
    "platt_huge": "calibration.b",
    "threshold": "classifier.threshold",
    "index": "outside the bank",
    "nan": "NaN",
    "meta_list": "format",
    "no_offsets": "data_offsets",
    "str_entry": "features.index",
    "kind": "unknown classifier kind",
    "version": "newer than this torchtrack",
    "nochecksum": "checksum",
    "sel": "selected_features",
    "objbox": "object_box",
    "name": "name must be",
}

MODEL_FILES_BAD = {
    "trunc": "truncated",
    "trail": "trailing bytes",
    "junk": "truncated or not a safetensors",
    "tiny": "only 2 bytes",
    "bitflip": "checksum",
    "missing": "does not exist",
}

# ----------------------------------------------------------------------------- track
T = "track {c}/frames --no-progress"
HB = "--tracker histogram:n_particles=50 --box 10,14,14,20"

CASES: list[Case] = [
    # output paths, checked before any work
    E("track-out-is-dir", f"{T} {HB} -o {{o}}", "is an existing folder"),
    E("track-device-unknown", f"{T} {HB} --device tpu -o {{o}}/t.csv", "expected 'cpu', 'cuda'"),
    # torch accepts "cpu:3", which then meant the one CPU, silently
    E("track-device-cpu-index", f"{T} {HB} --device cpu:3 -o {{o}}/t.csv", "the CPU is one device"),
    *(
        []
        if torch.cuda.is_available()
        else [E("track-device-no-cuda", f"{T} {HB} --device cuda -o {{o}}/t.csv", "no CUDA")]
    ),
    E("track-out-parent-missing", f"{T} {HB} -o {{o}}/no/such/out.csv", "does not exist"),
    E("track-out-parent-is-file", f"{T} {HB} -o {{c}}/afile/out.csv", "is not a folder"),
    E("track-out-empty", f"{T} {HB} -o ''", "empty path"),
    E("track-video-is-dir", f"{T} {HB} --video {{c}}/frames", "is an existing folder"),
    E("track-video-xyz", f"{T} {HB} --video {{o}}/out.xyz", r"must end in \.mp4 or \.avi"),
    E("track-video-no-ext", f"{T} {HB} --video {{o}}/out", r"must end in \.mp4 or \.avi"),
    E("track-video-parent-missing", f"{T} {HB} --video {{o}}/x/y.mp4", "does not exist"),
    E("track-out-equals-video", f"{T} {HB} -o {{o}}/a.mp4 --video {{o}}/a.mp4", "same file"),
    E("track-video-is-source", f"track {{c}}/clip.mp4 {HB} --video {{c}}/clip.mp4", "same file"),
    E("track-out-is-source", f"track {{c}}/clip.mp4 {HB} -o {{c}}/clip.mp4", "same file"),
    # boxes
    E("track-box-outside", f"{T} --tracker camshift --box 500,500,10,10 -o {{o}}/b.csv", "outside"),
    E(
        "track-box-zero",
        f"{T} --tracker camshift --box 1,1,0,10 -o {{o}}/b.csv",
        "zero or negative",
    ),
    E(
        "track-box-negative",
        f"{T} --tracker camshift --box 1,1,-4,10 -o {{o}}/b.csv",
        "zero or negative",
    ),
    E("track-box-nan", f"{T} --tracker camshift --box 1,nan,4,10 -o {{o}}/b.csv", "finite"),
    E("track-box-inf", f"{T} --tracker camshift --box 1,2,inf,10 -o {{o}}/b.csv", "finite"),
    E("track-box-three", f"{T} --tracker camshift --box 1,2,3 -o {{o}}/b.csv", "four numbers"),
    E("track-box-five", f"{T} --tracker camshift --box 1,2,3,4,5 -o {{o}}/b.csv", "four numbers"),
    E("track-box-text", f"{T} --tracker camshift --box a,b,c,d -o {{o}}/b.csv", "four numbers"),
    E("track-box-empty", f"{T} --tracker camshift --box '' -o {{o}}/b.csv", "four numbers"),
    E(  # was the box 1,2,3,4: the value after the gap read one place early
        "track-box-empty-value",
        f"{T} --tracker camshift --box 1,,2,3,4 -o {{o}}/b.csv",
        "--box '1,,2,3,4' has an empty value",
    ),
    E(  # float() read '1_0' as 10, where the box files refuse it
        "track-box-underscore",
        f"{T} --tracker camshift --box 1_0,2,3,4 -o {{o}}/b.csv",
        "four numbers x,y,w,h .*got '1_0,2,3,4'",
    ),
    E(
        "track-box-subpixel",
        f"{T} --tracker camshift --box 1,1,0.2,0.2 -o {{o}}/b.csv",
        "under one pixel|size below",
    ),
    A(
        "track-box-sticks-out",
        f"{T} --tracker camshift --box 55,10,20,20 -o {{o}}/b.csv",
        "clipped",
        ("b.csv",),
    ),
    # sources
    E("track-source-missing", f"track {{c}}/nothing {HB} -o {{o}}/b.csv", "does not exist"),
    E("track-source-empty-dir", f"track {{c}}/emptydir {HB} -o {{o}}/b.csv", "holds no image file"),
    E("track-source-notes-only", f"track {{c}}/notes {HB} -o {{o}}/b.csv", "holds no image file"),
    E(
        "track-source-mot-sequence",
        f"track {{c}}/motseq {HB} -o {{o}}/b.csv",
        r"holds no image file .*MOTChallenge sequence: give its img1/ folder, .*motseq/img1$",
    ),
    E(
        "track-source-corrupt",
        f"track {{c}}/corrupt {HB} -o {{o}}/b.csv --video {{o}}/v.mp4",
        # the first frame's reason too (it said only 'no readable frame')
        r"no readable frame in .*corrupt: nothing was tracked \(image .*\.jpg cannot be decoded",
    ),
    E(
        "track-source-1x1",
        "track {c}/tiny --tracker camshift --box 0,0,1,1 -o {o}/b.csv",
        "too small",
    ),
    E(
        "track-source-empty-video",
        f"track {{c}}/empty.mp4 {HB} -o {{o}}/b.csv",
        "cannot be opened|no readable frame",
    ),
    E(
        "track-source-text-video",
        f"track {{c}}/text.mp4 {HB} -o {{o}}/b.csv",
        "cannot be opened|no readable frame",
    ),
    E(
        "track-source-zero-frame-video",
        f"track {{c}}/zero.avi {HB} -o {{o}}/b.csv",
        r"no readable frame in .*zero\.avi: nothing was tracked \(it holds no frame\)$",
    ),
    E("track-source-camera", f"track 97 {HB} -o {{o}}/b.csv", "camera index 97"),
    E(  # one truncated JPEG as the source: OpenCV's video reader gave it grey-filled, tracked
        "track-source-one-truncated-jpeg",
        f"track {{c}}/jpgs/0002.jpg {HB} -o {{o}}/b.csv",
        r"no readable frame in .*0002\.jpg: nothing was tracked \(image .*0002\.jpg is truncated",
    ),
    A(
        "track-truncated-jpeg",
        f"track {{c}}/jpgs {HB} -o {{o}}/b.csv",
        "1 unreadable frame",
        ("b.csv",),
    ),
    A(
        "track-truncated-video",
        f"track {{c}}/cut.avi {HB} -o {{o}}/b.csv",
        "the video ended early",
        ("b.csv",),
    ),
    E(
        "track-unopenable-video",
        f"track {{c}}/cut.mp4 {HB} -o {{o}}/b.csv",
        "cannot be opened .*moov atom not found",
    ),
    A("track-video-out", f"{T} {HB} --video {{o}}/v.avi", "wrote", ("v.avi",)),
    # trackers and options
    E("track-tracker-unknown", f"{T} --tracker sift --box 10,14,14,20", "unknown tracker 'sift'"),
    # no --box: the first-frame scan cannot fit the 48x64 frames, and its hint was to 'scan
    # with min_scale <= ...', which no option of track sets
    E(
        "track-single-no-box-frames-below-window",
        f"{T} --tracker camshift -o {{o}}/b.csv",
        r"the 'pedestrian' detector cannot look for the target on the first frame \(frame 48x64 "
        r".*\): give the target's box with --box x,y,w,h \(.*0000\.png\)$",
    ),
    E(
        "track-tracker-spec",
        f"{T} --tracker histogram:n_particles --box 10,14,14,20",
        "not key=value",
    ),
    E("track-tracker-noname", f"{T} --tracker :a=1 --box 10,14,14,20", "has no name"),
    E("track-tracker-param", f"{T} --tracker camshift:wings=2 --box 10,14,14,20", "no parameter"),
    E(
        "track-particles-neg",
        f"{T} --tracker histogram:n_particles=-5 --box 10,14,14,20",
        r"histogram tracker: n_particles must be >= 1, got -5",
    ),
    E(
        "track-particles-text",
        f"{T} --tracker histogram:n_particles=many --box 10,14,14,20",
        r"histogram tracker: 'n_particles' must be an integer, got 'many'",
    ),
    E(
        "track-particles-zero",
        f"{T} --tracker adaptive-haar:n_particles=0 --box 10,14,14,20",
        r"adaptive-haar tracker: n_particles must be >= 1, got 0",
    ),
    E(
        "track-adapt-wrong-tracker",
        f"{T} --tracker camshift --adapt global --box 10,14,14,20",
        "does not take --adapt",
    ),
    E(
        "track-adapt-bad",
        f"{T} --tracker adaptive-haar --adapt sideways --box 10,14,14,20",
        "invalid choice",
        2,
    ),
    E(
        "track-config-missing",
        f"{T} --tracker histogram --config {{c}}/none.toml --box 10,14,14,20",
        "cannot read tracker config .*No such file",
    ),
    E(
        "track-config-unknown-key",
        f"{T} --tracker histogram --config {{c}}/tracker_unknown.toml --box 10,14,14,20",
        "surprise",
    ),
    E(
        "track-config-bad-toml",
        f"{T} --tracker histogram --config {{c}}/bad.toml --box 10,14,14,20",
        "TOML|toml",
    ),
    *(
        E(
            f"track-config-deep-{name}",
            f"{T} --tracker {name} --config {{c}}/deep.toml --box 10,14,14,20 -o {{o}}/b.csv",
            "nests arrays or tables too deeply to read",
        )
        for name in ("histogram", "cotrain")
    ),
    E(
        "track-dynamics-deep",
        f"{T} --tracker multi:dynamics={{c}}/deep.toml -o {{o}}/b.csv",
        r"dynamics config .*deep\.toml': it nests arrays or tables too deeply to read",
    ),
    E("track-max-frames-0", f"{T} {HB} --max-frames 0", "--max-frames must be >= 1"),
    E("track-max-frames-text", f"{T} {HB} --max-frames ten", "must be an integer, got 'ten'", 2),
    # int() / float() read '1_0' as 10: 10 frames tracked, detections below 5 dropped
    E("track-max-frames-underscore", f"{T} {HB} --max-frames 1_0", "got '1_0'", 2),
    # int() reads Arabic-Indic digits as a number: 3 frames tracked from '\u0663'
    E("track-max-frames-non-ascii", f"{T} {HB} --max-frames \u0663", "must be an integer", 2),
    E(
        "track-det-min-score-underscore",
        "track {c}/frames --detections {c}/det.txt --det-min-score 0_5 --mot {o}/m.txt",
        "argument --det-min-score: must be a number, got '0_5'",
        2,
    ),
    E("track-threads-0", f"{T} {HB} --threads 0", "--threads must be >= 1"),
    # one source: no backend is built, and -1 was accepted and ignored
    E(
        "track-max-retries-negative",
        f"{T} {HB} -o {{o}}/b.csv --max-retries -1",
        r"--max-retries must be >= 0, got -1",
    ),
    E(  # every source failed in turn, each with this error, and a manifest was left
        "track-corpus-tracker-key",
        f"{T} --tracker multi:bogus=2 --out-dir {{o}}/runs",
        r"multi-target tracker: unknown key\(s\) 'bogus'",
    ),
    E(
        "track-corpus-box",
        f"{T} --tracker camshift --box 1,,2,3,4 --out-dir {{o}}/runs",
        "--box '1,,2,3,4' has an empty value",
    ),
    E(
        "track-corpus-max-retries-negative",
        f"{T} {HB} --out-dir {{o}}/runs --max-retries -1",
        r"--max-retries must be >= 0, got -1",
    ),
    E(
        "track-particles-no-video",
        f"{T} {HB} --particles -o {{o}}/b.csv",
        r"--particles draws into the annotated video: give --video FILE too$",
    ),
    E("track-color-bad", f"{T} {HB} --color cmyk", "invalid choice", 2),
    E("track-detect-unknown", f"{T} --detect zebra", "unknown model 'zebra'"),
    E("track-detect-missing-file", f"{T} --detect {{c}}/none.safetensors", "does not exist"),
    E(
        "track-detect-with-box",
        f"{T} --tracker camshift --detect pedestrian --box 10,14,14,20",
        "--detect",
    ),
    E("track-trusted-key-junk", f"{T} {HB} --trusted-key {{c}}/junk.pub", "not a PEM public key"),
    E("track-trusted-key-missing", f"{T} {HB} --trusted-key {{c}}/none.pub", "cannot be read"),
    E(
        "track-unsigned-required",
        f"{T} --tracker detector:model={{c}}/toy.safetensors --box 10,14,14,20 --require-signed -o {{o}}/b.csv",
        "not signed",
    ),
    E(
        "track-untrusted-signer",
        f"{T} --tracker detector:model={{c}}/signed.safetensors --box 10,14,14,20 --trusted-key {{c}}/mallory.pub -o {{o}}/b.csv",
        "not trusted here",
    ),
    E(
        "track-forged-signed",
        f"{T} --tracker detector:model={{c}}/forged_signed.safetensors --box 10,14,14,20 -o {{o}}/b.csv --trusted-key {{c}}/alice.pub",
        "does not verify",
    ),
    E(
        "track-uncalibrated",
        f"{T} --tracker detector:model={{c}}/uncal.safetensors --box 10,14,14,20 -o {{o}}/b.csv",
        "calibrat",
    ),
    E("track-seed-text", f"{T} {HB} --seed x", "--seed: must be an integer", 2),
    E("track-no-source", "track", "required|SOURCE", 2),
]
for name, msg in FORGED_MSG.items():
    CASES.append(
        E(
            f"track-forged-{name}",
            f"{T} --tracker detector:model={{c}}/forged_{name}.safetensors --box 10,14,14,20 -o {{o}}/b.csv",
            msg,
        )
    )

# ---------------------------------------------------------------------------- detect
D = "detect {c}/toy.safetensors {c}/frames -q"
CASES += [
    E("detect-out-dir", f"{D} -o {{c}}/frames", "is an existing folder"),
    E("detect-out-parent", f"{D} -o {{o}}/x/d.jsonl", "does not exist"),
    # a folder not made yet: Path() dropped the slash and the file 'new' was written
    E("detect-out-slash", f"{D} -o {{o}}/new/", r"--out '.*new/' ends in '/', a folder"),
    E(
        "cal-json-slash",
        "calibrate --scores {c}/scores.csv --json {o}/new/",
        r"--json '.*new/' ends in '/', a folder",
    ),
    E("detect-annotate-file", f"{D} --annotate {{c}}/afile", "is an existing file"),
    E("detect-annotate-parent", f"{D} --annotate {{o}}/x/y", "does not exist"),
    # 0001.jpg and 0001.png: both annotated as 0001.png, the first lost without a word
    E(
        "detect-annotate-same-stem",
        "detect {c}/toy.safetensors {c}/samestem -q -o {o}/d.jsonl --annotate {o}/ann",
        r"--annotate .* writes each frame as <its name>\.png: .*samestem/0001\.jpg and "
        r".*samestem/0001\.png would both be 0001\.png",
    ),
    E("detect-video-avi", f"{D} --video {{o}}/v.avi", r"\.mp4"),
    E("detect-video-dir", f"{D} --video {{c}}/frames", r"\.mp4|existing folder"),
    E("detect-out-equals-video", f"{D} -o {{o}}/v.mp4 --video {{o}}/v.mp4", "same file"),
    E(
        "detect-out-equals-annotate",
        f"{D} -o {{o}}/a --annotate {{o}}/a",
        r"--out and --annotate name the same file '.*/a'",
    ),
    E(
        "detect-video-equals-annotate",
        f"{D} --video {{o}}/a.mp4 --annotate {{o}}/a.mp4",
        r"--video and --annotate name the same file '.*/a\.mp4'",
    ),
    E("detect-threshold-2", f"{D} --threshold 2", "--threshold is a probability"),
    E("detect-threshold-nan", f"{D} --threshold nan", "--threshold is a probability"),
    E("detect-min-scale-0", f"{D} --min-scale 0", "--min-scale must be > 0"),
    # frames upsampled 100x asked for lattices of tens of GB; 1e-308 was an OverflowError
    E("detect-min-scale-tiny", f"{D} --min-scale 1e-308", r"at most 16x: --min-scale 0.0625"),
    E("detect-min-height-tiny", f"{D} --min-height 0.5", r"--min-height 0.5 px .* at most 16x"),
    E("detect-max-below-min", f"{D} --min-scale 2 --max-scale 1", "below --min-scale"),
    E("detect-nms-0", f"{D} --nms-iou 0", "--nms-iou"),
    E("detect-batch-0", f"{D} --batch 0", r"--batch must be in \[1, 64\], got 0"),
    # 300 frames at once asked for gigabytes in one allocation (a RuntimeError traceback)
    E("detect-batch-huge", f"{D} --batch 100000", r"--batch must be in \[1, 64\]"),
    E("detect-max-frames-0", f"{D} --max-frames 0", "--max-frames must be >= 1"),
    E("detect-threads-0", f"{D} --threads 0", "--threads must be >= 1"),
    E(
        "detect-source-missing",
        "detect {c}/toy.safetensors {c}/none -o {o}/d.jsonl",
        "does not exist",
    ),
    E(
        "detect-source-empty",
        "detect {c}/toy.safetensors {c}/emptydir -o {o}/d.jsonl",
        "holds no image file",
    ),
    E(
        "detect-source-corrupt",
        "detect {c}/toy.safetensors {c}/corrupt -o {o}/d.jsonl --annotate {o}/ann",
        "no frame of",
    ),
    E(
        "detect-source-1x1",
        "detect {c}/toy.safetensors {c}/tiny -o {o}/d.jsonl",
        "no frame of|smaller",
    ),
    E(
        "detect-source-text-video",
        "detect {c}/toy.safetensors {c}/text.mp4 -o {o}/d.jsonl",
        "cannot be opened|no frame",
    ),
    E(
        "detect-source-zero-frame-video",
        "detect {c}/toy.safetensors {c}/zero.avi -o {o}/d.jsonl",
        r"no frame of .*zero\.avi could be processed \(it holds no frame\)$",
    ),
    E(
        "detect-strict-truncated",
        "detect {c}/toy.safetensors {c}/jpgs -o {o}/d.jsonl --strict",
        r"0002\.jpg is truncated",
    ),
    A(
        "detect-truncated-skipped",
        "detect {c}/toy.safetensors {c}/jpgs -o {o}/d.jsonl",
        r"skipped frame 2: .*0002\.jpg is truncated",
        ("d.jsonl",),
    ),
    A(
        "detect-truncated-video",
        "detect {c}/toy.safetensors {c}/cut.avi -o {o}/d.jsonl",
        "ended early",
        ("d.jsonl",),
    ),
    E(
        "detect-strict-truncated-video",
        "detect {c}/toy.safetensors {c}/cut.avi -o {o}/d.jsonl --strict",
        "ended at frame",
    ),
    A(
        "detect-one-image",
        "detect {c}/toy.safetensors {c}/photo.png -o {o}/d.jsonl",
        "frame",
        ("d.jsonl",),
    ),
    E(
        "detect-uncalibrated",
        "detect {c}/uncal.safetensors {c}/frames -o {o}/d.jsonl",
        "no calibration",
    ),
    E("detect-model-unknown", "detect zebra {c}/frames", "unknown model 'zebra'"),
    E(
        "detect-model-is-dir",
        "detect {c}/frames {c}/frames -o {o}/d.jsonl",
        "is a folder|not a torchtrack|does not exist",
    ),
    E("detect-require-unsigned", f"{D} --require-signed -o {{o}}/d.jsonl", "not signed"),
    E(
        "detect-untrusted",
        "detect {c}/signed.safetensors {c}/frames --trusted-key {c}/mallory.pub -o {o}/d.jsonl",
        "not trusted here",
    ),
    A(
        "detect-trusted",
        "detect {c}/signed.safetensors {c}/frames --trusted-key {c}/alice.pub -o {o}/d.jsonl",
        "frame",
        ("d.jsonl",),
    ),
    E(
        "detect-forged-signed",
        "detect {c}/forged_signed.safetensors {c}/frames -o {o}/d.jsonl --trusted-key {c}/alice.pub",
        "does not verify",
    ),
    # signatures optional and the signer unknown here: it loads like an unsigned file (the
    # checksum and range checks still hold); trusting the signer's key is what catches it
    A(
        "detect-forged-signed-untrusted",
        "detect {c}/forged_signed.safetensors {c}/frames -o {o}/d.jsonl",
        "frame",
        ("d.jsonl",),
    ),
    E(
        "detect-forged-signed-required",
        "detect {c}/forged_signed.safetensors {c}/frames -o {o}/d.jsonl --require-signed",
        "not trusted here",
    ),
    E("detect-missing-args", "detect", "required|MODEL", 2),
]
for name, msg in {**FORGED_MSG, **MODEL_FILES_BAD}.items():
    f = f"forged_{name}" if name in FORGED_MSG else name
    CASES.append(
        E(
            f"detect-model-{name}",
            f"detect {{c}}/{f}.safetensors {{c}}/frames -o {{o}}/d.jsonl",
            msg,
        )
    )

# ----------------------------------------------------------------------------- train
TR = "train --pos {c}/crops/pos --neg {c}/crops/neg --window 16 16 --features 4 -q"
CASES += [
    E("train-out-dir", f"{TR} -o {{c}}/frames", "is an existing folder"),
    E("train-out-parent", f"{TR} -o {{o}}/a/b.safetensors", "does not exist"),
    E("train-out-parent-file", f"{TR} -o {{c}}/afile/m.safetensors", "is not a folder"),
    E("train-no-out", "train --pos {c}/crops/pos", "required|--out", 2),
    E("train-no-pos", "train -o {o}/m.safetensors", "give --config TOML, or --pos"),
    E(
        "train-no-neg",
        "train --pos {c}/crops/pos --window 16 16 -o {o}/m.safetensors",
        "no negatives",
    ),
    E(
        "train-pos-missing",
        "train --pos {c}/none --neg {c}/crops/neg --window 16 16 -o {o}/m.safetensors",
        "does not exist",
    ),
    E(
        "train-pos-empty",
        "train --pos {c}/emptydir --neg {c}/crops/neg --window 16 16 -o {o}/m.safetensors",
        "no usable image",
    ),
    E(
        "train-pos-corrupt",
        "train --pos {c}/badcrops --neg {c}/crops/neg --window 16 16 -o {o}/m.safetensors",
        "no usable image",
    ),
    E(
        "train-pos-corrupt-strict",
        "train --pos {c}/badcrops --neg {c}/crops/neg --window 16 16 --strict -o {o}/m.safetensors",
        "unusable file",
    ),
    E(
        "train-few",
        "train --pos {c}/few/pos --neg {c}/few/neg --window 16 16 --features 4 -q -o {o}/m.safetensors",
        "too little data.*fewer than the minimum 20",
    ),
    E("train-holdout-99", f"{TR} --holdout 0.99 -o {{o}}/m.safetensors", "too little data"),
    E(
        "train-holdout-tiny",
        f"{TR} --holdout 0.01 -o {{o}}/m.safetensors",
        "calibration crops, fewer than the minimum 10",
    ),
    E("train-holdout-1.5", f"{TR} --holdout 1.5 -o {{o}}/m.safetensors", "calibration_fraction"),
    E("train-holdout-0", f"{TR} --holdout 0 -o {{o}}/m.safetensors", "calibration_fraction"),
    E(
        "train-flat",
        "train --pos {c}/flat/pos --neg {c}/crops/neg --window 16 16 --features 4 -q -o {o}/m.safetensors",
        "are flat",
    ),
    E("train-features-0", f"{TR} --features 0 -o {{o}}/m.safetensors", "n_features"),
    E(
        "train-mining-rounds-huge",  # ran for ever: each round scans and retrains
        f"{TR} --neg-images {{c}}/frames --mining-rounds 2000000000 -o {{o}}/m.safetensors",
        r"mining.rounds must be in \[0, 100\]",
    ),
    E(
        "train-features-with-channels",
        f"{TR} --bank channels -o {{o}}/m.safetensors",
        "--features 4 sets how many features AdaBoost selects",
    ),
    E(
        "train-window-0",
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 0 16 -o {o}/m.safetensors",
        "window",
    ),
    E(
        "train-window-small",
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 3 3 -q -o {o}/m.safetensors",
        "filter size|window|sizes",
    ),
    E(
        "train-config-missing",
        "train --config {c}/none.toml -o {o}/m.safetensors",
        "does not exist",
    ),
    E("train-config-bad", "train --config {c}/bad.toml -o {o}/m.safetensors", "not valid TOML"),
    E("train-config-unknown", "train --config {c}/unknown.toml -o {o}/m.safetensors", "surprise"),
    E(
        "train-mining-no-images",
        f"{TR} --mining-rounds 1 -o {{o}}/m.safetensors",
        "needs data.negative_images",
    ),
    E(
        "train-random-neg",
        "train --pos {c}/crops/pos --neg-images {c}/frames --random-negatives -5 --window 16 16 -o {o}/m.safetensors",
        "data.random_negatives must be in \\[0, 10000000\\] .*got -5",
    ),
    E(
        "train-exclude-missing",
        f"{TR} --exclude {{c}}/none.txt -o {{o}}/m.safetensors",
        "does not exist",
    ),
    E(
        "train-classifier-bad",
        f"{TR} --classifier tree -o {{o}}/m.safetensors",
        "invalid choice",
        2,
    ),
    E(
        "train-neg-images-missing",
        "train --pos {c}/crops/pos --neg-images {c}/none --random-negatives 50 --window 16 16 -q -o {o}/m.safetensors",
        "does not exist",
    ),
    E(
        "train-few-svm",
        "train --pos {c}/few/pos --neg {c}/few/neg --window 16 16 --features 4 --classifier svm "
        "-q -o {o}/m.safetensors",
        "too little data",
    ),
    A(
        "train-few-forced",
        "train --pos {c}/few/pos --neg {c}/crops/neg --window 16 16 --features 4 --holdout 0.5 --force -q -o {o}/m.safetensors",
        "wrote",
        ("m.safetensors",),
    ),
]

# ------------------------------------------------------------------------- calibrate
CS = "calibrate --scores {c}/scores.csv -q"
CM = "calibrate {c}/toy.safetensors --pos {c}/crops/pos --neg {c}/crops/neg -q"
CASES += [
    E("cal-neither", "calibrate", "nothing to calibrate"),
    E(
        "cal-both",
        "calibrate {c}/toy.safetensors --scores {c}/scores.csv --json {o}/p.json",
        "give either a MODEL",
    ),
    E("cal-scores-no-json", CS, "needs --json"),
    E("cal-json-dir", f"{CS} --json {{c}}/frames", "is an existing folder"),
    E("cal-json-parent", f"{CS} --json {{o}}/x/p.json", "does not exist"),
    E("cal-plot-suffix", f"{CS} --json {{o}}/p.json --plot {{o}}/p.txt", r"must end in \.png"),
    E("cal-plot-dir", f"{CS} --json {{o}}/p.json --plot {{c}}/frames", "is an existing folder"),
    E("cal-json-equals-plot", f"{CS} --json {{o}}/p.png --plot {{o}}/p.png", "same file"),
    E("cal-json-is-scores", f"{CS} --json {{c}}/scores.csv", "same file"),
    E(
        "cal-scores-missing",
        "calibrate --scores {c}/none.csv --json {o}/p.json",
        "cannot read score file",
    ),
    E("cal-scores-empty", "calibrate --scores {c}/empty.csv --json {o}/p.json", "has no rows"),
    E("cal-scores-header", "calibrate --scores {c}/header.csv --json {o}/p.json", "no data rows"),
    E("cal-scores-nan", "calibrate --scores {c}/nan.csv --json {o}/p.json", "non-finite"),
    E("cal-scores-text", "calibrate --scores {c}/text.csv --json {o}/p.json", "not numbers"),
    E(
        "cal-scores-one-label",
        "calibrate --scores {c}/onelabel.csv --json {o}/p.json",
        "label|class",
    ),
    E(
        "cal-scores-three-labels",
        "calibrate --scores {c}/threelabels.csv --json {o}/p.json",
        "label|class",
    ),
    E("cal-scores-latin1", "calibrate --scores {c}/latin1.csv --json {o}/p.json", "not UTF-8"),
    E("cal-scores-one-col", "calibrate --scores {c}/cols.csv --json {o}/p.json", "columns"),
    E(
        "cal-scores-few",
        "calibrate --scores {c}/scores3.csv --json {o}/p.json",
        "too little data to calibrate",
    ),
    A(
        "cal-scores-few-forced",
        "calibrate --scores {c}/scores3.csv --json {o}/p.json --force --min-per-class 1",
        "wrote",
        ("p.json",),
    ),
    A(
        "cal-scores-ok",
        f"{CS} --json {{o}}/p.json --plot {{o}}/r.png",
        "wrote",
        ("p.json", "r.png"),
    ),
    E("cal-bins-0", f"{CS} --json {{o}}/p.json --bins 0", r"--bins must be in \[1, 1000\]"),
    # 2e9 bins: a 16 GB allocation failed as a RuntimeError traceback; 1e20 an OverflowError
    E("cal-bins-huge", f"{CS} --json {{o}}/p.json --bins 2000000000", "--bins must be in"),
    E("cal-bins-huger", f"{CS} --json {{o}}/p.json --bins 99999999999999999999", "--bins must"),
    E("cal-min-0", f"{CS} --json {{o}}/p.json --min-per-class 0", "--min-per-class must be >= 1"),
    E("cal-method-bad", f"{CS} --json {{o}}/p.json --method beta", "invalid choice", 2),
    E("cal-scores-with-pos", f"{CS} --json {{o}}/p.json --pos {{c}}/crops/pos", "need a MODEL"),
    E(
        "cal-model-no-crops",
        "calibrate {c}/toy.safetensors -o {o}/m.safetensors",
        "needs labelled calibration crops",
    ),
    E("cal-model-out-dir", f"{CM} -o {{c}}/frames", "is an existing folder"),
    E(  # meant --json: the calibrated model was written, binary, into cal.json
        "cal-model-out-not-a-model",
        f"{CM} -o {{o}}/cal.json",
        r"--out '.*cal.json' must end in .safetensors, got .json",
    ),
    E(
        "cal-model-few",
        "calibrate {c}/toy.safetensors --pos {c}/few/pos --neg {c}/few/neg -o {o}/m.safetensors",
        "too little data to calibrate",
    ),
    E(
        "cal-model-pos-missing",
        "calibrate {c}/toy.safetensors --pos {c}/none --neg {c}/crops/neg -o {o}/m.safetensors",
        "does not exist",
    ),
    E("cal-model-region", f"{CM} --region 0 0 8 8 -o {{o}}/m.safetensors", "go together"),
    E(
        "cal-model-file-missing",
        "calibrate {c}/none.safetensors --pos {c}/crops/pos --neg {c}/crops/neg -o {o}/m.safetensors",
        "does not exist",
    ),
    E(
        "cal-model-forged-signed",
        "calibrate {c}/forged_signed.safetensors --pos {c}/crops/pos --neg {c}/crops/neg -o {o}/m.safetensors --trusted-key {c}/alice.pub",
        "does not verify",
    ),
    E("cal-model-require", f"{CM} --require-signed -o {{o}}/m.safetensors", "not signed"),
    E(
        "cal-model-inverted",
        f"{CM} -o {{o}}/m.safetensors --plot {{o}}/r.png",
        "negatives higher; are --pos and --neg swapped",
    ),
    # the toy detector (random stumps) happens to score the noise crops higher than the bars
    A(
        "cal-model-ok",
        "calibrate {c}/toy.safetensors --pos {c}/crops/neg --neg {c}/crops/pos -q "
        "-o {o}/m.safetensors --plot {o}/r.png",
        "wrote",
        ("m.safetensors", "r.png"),
    ),
]
for name, msg in {**FORGED_MSG, **MODEL_FILES_BAD}.items():
    f = f"forged_{name}" if name in FORGED_MSG else name
    CASES.append(
        E(
            f"cal-model-{name}",
            f"calibrate {{c}}/{f}.safetensors --pos {{c}}/crops/pos --neg {{c}}/crops/neg -o {{o}}/m.safetensors",
            msg,
        )
    )

# ------------------------------------------------------------------------------ eval
EV = "eval --sequences {c}/seqs --trackers camshift --no-progress"
CASES += [
    E("eval-out-file", f"{EV} -o {{c}}/afile", "is an existing file"),
    E("eval-device-unknown", f"{EV} --device gpu0 -o {{o}}/e", "expected 'cpu', 'cuda'"),
    *(
        []
        if torch.cuda.is_available()
        else [E("eval-device-no-cuda", f"{EV} --device cuda -o {{o}}/e", "no CUDA")]
    ),
    E("eval-out-parent", f"{EV} -o {{o}}/a/b", "does not exist"),
    E("eval-out-inside-sequences", f"{EV} -o {{c}}/seqs/res", "inside the input folder"),
    E("eval-out-is-sequences", f"{EV} -o {{c}}/seqs", "is the input folder --sequences"),
    E("eval-no-out", EV, "needs --out"),
    E("eval-no-sequences", "eval --trackers camshift -o {o}/r", "needs --sequences"),
    E("eval-no-trackers", "eval --sequences {c}/seqs -o {o}/r", "needs --trackers"),
    E(
        "eval-sequences-missing",
        "eval --sequences {c}/none --trackers camshift -o {o}/r",
        "does not exist",
    ),
    E(
        "eval-no-sequence-found",
        "eval --sequences {c}/noseq --trackers camshift -o {o}/r",
        "no tracking sequence",
    ),
    E("eval-gt-mismatch", "eval --sequences {c}/badgt --trackers camshift -o {o}/r", "rows|frames"),
    E("eval-gt-text", "eval --sequences {c}/textgt --trackers camshift -o {o}/r", "line 2"),
    E("eval-tracker-unknown", f"{EV} --trackers sift -o {{o}}/r", "unknown tracker 'sift'"),
    E("eval-tracker-multi-on-sequences", f"{EV} --trackers multi -o {{o}}/r", "--mot SEQ"),
    E("eval-tracker-param", f"{EV} --trackers camshift:wings=1 -o {{o}}/r", "no parameter"),
    E("eval-max-frames-1", f"{EV} --max-frames 1 -o {{o}}/r", "--max-frames must be >= 2"),
    E("eval-jobs-0", f"{EV} --jobs 0 -o {{o}}/r", "--jobs must be >= 1"),
    E(
        "eval-max-retries-negative",
        f"{EV} --max-retries -1 -o {{o}}/r",
        "--max-retries must be >= 0",
    ),
    E(
        "eval-import-missing",
        f"{EV} --import no_such_module_x -o {{o}}/r",
        "cannot import tracker module",
    ),
    E("eval-invisible-bad", f"{EV} --invisible maybe -o {{o}}/r", "invalid choice", 2),
    E("eval-trusted-junk", f"{EV} --trusted-key {{c}}/junk.pub -o {{o}}/r", "not a PEM public key"),
    A(
        "eval-truncate",
        "eval --sequences {c}/badgt --trackers camshift --on-mismatch truncate --no-progress -o {o}/r",
        "results",
        ("r/results.json", "r/results.md", "r/sequences/short/camshift.json"),
    ),
]

# -------------------------------------------------------- multi-target track and MOT eval
MT = "track {c}/frames --no-progress --tracker multi"
CASES += [
    E(
        "mot-out-dir",
        f"{MT} --detections {{c}}/det.txt --mot {{c}}/frames",
        "is an existing folder",
    ),
    E("mot-out-parent", f"{MT} --detections {{c}}/det.txt --mot {{o}}/x/m.txt", "does not exist"),
    E(
        "mot-equals-out",
        f"{MT} --detections {{c}}/det.txt --mot {{o}}/m.txt -o {{o}}/m.txt",
        "same file",
    ),
    # the rows stream into PATH.part: the CSV ended in x.csv and no x.csv.part was left, while
    # both were reported written
    E(
        "track-out-is-mots-part",
        f"{MT} --detections {{c}}/det.txt -o {{o}}/x.csv.part --mot {{o}}/x.csv",
        r"--out and --mot's temporary file name the same file '.*x\.csv\.part'",
    ),
    E(
        "track-out-part-is-detections",
        f"{MT} --detections {{c}}/det.txt.part --mot {{c}}/det.txt",
        r"--mot's temporary file '.*det\.txt\.part' is the input --detections",
    ),
    E("mot-det-missing", f"{MT} --detections {{c}}/none.txt --mot {{o}}/m.txt", "does not exist"),
    E("mot-det-malformed", f"{MT} --detections {{c}}/det_bad.txt --mot {{o}}/m.txt", "line 2"),
    E("mot-det-zero-box", f"{MT} --detections {{c}}/det_zero.txt --mot {{o}}/m.txt", "line 1"),
    E(
        "mot-det-calibration-deep",
        f"{MT} --detections {{c}}/det.txt --det-calibration {{c}}/deep.json --mot {{o}}/m.txt",
        r"--det-calibration .*deep\.json' is not a calibration JSON .*recursion",
    ),
    E(
        "mot-det-calibration-alone",
        f"{MT} --det-calibration {{c}}/none.json --mot {{o}}/m.txt",
        "apply to --detections",
    ),
    E(
        "eval-mot-out-file",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt -o {c}/afile",
        "is an existing file",
    ),
    E(
        "eval-mot-out-inside",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt -o {c}/mot/TOY-01/gt",
        "inside the input folder --mot",
    ),
    E(
        "eval-mot-out-parent",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt -o {o}/a/b",
        "does not exist",
    ),
    E(
        "eval-mot-seq-missing",
        "eval --mot {c}/mot/NONE --results {c}/res.txt -o {o}/r",
        "does not exist|no MOT",
    ),
    E(
        "eval-mot-results-missing",
        "eval --mot {c}/mot/TOY-01 --results {c}/none.txt -o {o}/r",
        "does not exist|no results",
    ),
    E(
        "eval-mot-results-dup-id",
        "eval --mot {c}/mot/TOY-01 --results {c}/res_bad.txt -o {o}/r",
        "line 2",
    ),
    E("eval-mot-no-results", "eval --mot {c}/mot/TOY-01 -o {o}/r", "needs --mot SEQ"),
    # one results file given twice was scored as two trackers
    E(
        "eval-mot-results-twice",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt {c}/./res.txt -o {o}/r",
        r"--results gives '.*res\.txt' twice",
    ),
    E(
        "eval-mot-results-device",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt --device cuda:0 -o {o}/r",
        "--device do",
    ),
    E(
        "eval-mot-trackers-no-out",
        "eval --mot {c}/mot/TOY-01 --trackers multi",
        "needs -o/--out DIR",
    ),
    A(
        "mot-track-detections-mostly-outside",
        f"{MT} --detections {{c}}/det_tall.txt --mot {{o}}/m.txt",
        "no target was started from --detections",
        ("m.txt",),
    ),
    A(
        "mot-track-detections-twice",
        f"{MT} --detections {{c}}/det_twice.txt --mot {{o}}/m.txt",
        "1 target",
        ("m.txt",),
    ),
    A(
        "mot-track-ok",
        f"{MT} --detections {{c}}/det.txt --mot {{o}}/m.txt -o {{o}}/b.csv",
        "wrote",
        ("m.txt", "b.csv"),
    ),
    A(
        "eval-mot-ok",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt -o {o}/r",
        "HOTA|MOTA",
        ("r/results.json", "r/results.md"),
    ),
    E(
        "eval-mot-trackers-out-file",
        "eval --mot {c}/mot/TOY-01 --trackers multi -o {c}/afile",
        "is an existing file",
    ),
    E(
        "eval-mot-trackers-fail-on-a-later-sequence",
        "eval --mot {c}/mot2 --trackers multi -o {o}/r --no-progress",
        r"frame size changed from \(48, 64\) to \(40, 64\)",
    ),
    # seqinfo.ini's name is a file name (results are <name>.txt): never a path out of a folder
    E(
        "eval-mot-name-escapes",
        "eval --mot {c}/mot/ESCAPE --results {c}/res.txt -o {o}/r",
        "name='../escape' must be one plain file name",
    ),
    A(
        "eval-mot-name-percent",
        "eval --mot {c}/mot/PCT --results {c}/res.txt -o {o}/r",
        "a%b",
        ("r/results.json", "r/results.md"),
    ),
    E(
        "eval-mot-seqinfo-no-header",
        "eval --mot {c}/mot/NOHEADER --results {c}/res.txt",
        r"seqinfo\.ini is not a valid ini file: line 1 'name=TOY-01' comes before any section "
        r"header \(a seqinfo\.ini starts with \[Sequence\]\)$",
    ),
    E("eval-mot-seqinfo-binary", "eval --mot {c}/mot/BIN --results {c}/res.txt", "not a text file"),
    E(
        "eval-mot-seqlength-huge",
        "eval --mot {c}/mot/LONG --results {c}/res.txt",
        "seqLength=1000000000000 is more than 10000000 frames",
    ),
    E(
        "eval-mot-results-id-huge",
        "eval --mot {c}/mot/TOY-01 --results {c}/res_hugeid.txt -o {o}/r",
        "id 1e[+]19 is out of range",
    ),
    # outputs onto a named pipe (or a device such as /dev/null): refused, the pipe stays
    E("detect-out-pipe", "detect {c}/toy.safetensors {c}/frames -q -o {c}/pipe", "is a named pipe"),
    E(
        "track-mot-pipe",
        f"{MT} --detections {{c}}/det.txt --mot {{c}}/pipe",
        "--mot .* exists and is a named pipe",
    ),
    # values that would hang, overflow or exhaust memory
    E(
        "detect-scale-step-near-1",
        "detect {c}/toy.safetensors {c}/frames -q --scale-step 1.0000001 -o {o}/d.jsonl",
        "--scale-step must be a finite number >= 1.01",
    ),
    E(
        "track-multi-scale-step-near-1",
        f"{MT}:scan_scale_step=1.0000001 -o {{o}}/b.csv",
        "scan_scale_step must be a finite number >= 1.01",
    ),
    E("track-multi-int-huge", f"{MT}:max_lost=99999999999999999999 -o {{o}}/b.csv", "within"),
    E("track-multi-sigma-huge", f"{MT}:detection_sigma=1e308 -o {{o}}/b.csv", "at most 1"),
    E(
        "track-multi-particles-huge",
        f"{MT}:n_particles=1000000000 -o {{o}}/b.csv",
        "particles in all",
    ),
    E("track-multi-max-scale-nan", f"{MT}:scan_max_scale=nan -o {{o}}/b.csv", "finite"),
    E("track-multi-noise-scale-inf", f"{MT}:max_noise_scale=inf -o {{o}}/b.csv", "finite"),
    E("track-threads-huge", f"{T} {HB} --threads 99999999999999999999", "4 per CPU core"),
    E(
        "track-multi-dynamics-binary",
        f"{MT}:dynamics={{c}}/binary.toml -o {{o}}/b.csv",
        "not a text",
    ),
    E(
        "track-multi-dynamics-folder",
        f"{MT}:dynamics={{c}}/emptydir -o {{o}}/b.csv",
        "is a folder",
    ),
]

# ------------------------------------------------------------------------------ sign
CASES += [
    E("sign-nothing", "sign", "exactly one of"),
    # single-target settings that overflowed OpenCV or the search region, or did nothing
    E(
        "track-camshift-bins-huge",
        f"{T} --tracker camshift:bins=99999999999999999999 --box 10,14,14,20",
        r"camshift bins must be an integer in \[2, 256\]",
    ),
    E(
        "track-camshift-confidence-nan",
        f"{T} --tracker camshift:min_confidence=nan --box 10,14,14,20",
        "camshift min_confidence must be in",
    ),
    E(
        "track-camshift-iterations-huge",
        f"{T} --tracker camshift:max_iter=99999999999999 --box 10,14,14,20",
        "camshift max_iter must be an integer",
    ),
    E(
        "track-cotrain-search-huge",
        f"{T} --tracker cotrain:search_scale=1e308 --box 10,14,14,20",
        "search_scale",
    ),
    # absurd finite settings ran on as nonsense, overflowed to +inf weights, or raised a bare
    # ValueError inside the filter (cotrain motion_std)
    E(
        "track-haar-surround-huge",
        f"{T} --tracker adaptive-haar:n_particles=50,surround=1e308 --box 10,14,14,20",
        r"surround must be in \(1, 10\] \(times the centre side\), got 1e\+308",
    ),
    E(
        "track-detector-context-huge",
        f"{T} --tracker detector:context=1e308 --box 10,14,14,20",
        r"context \(window over box height\) must be in \(0, 10\]",
    ),
    E(
        "track-detector-power-huge",
        f"{T} --tracker detector:likelihood_power=1e308 --box 10,14,14,20",
        r"likelihood_power must be in \(0, 100\], got 1e\+308",
    ),
    E(
        "track-fused-det-weight-huge",
        f"{T} --tracker fused:det_weight=1e308 --box 10,14,14,20",
        r"det_weight must be in \[0, 100\], got 1e\+308",
    ),
    E(
        "track-fused-cotrain-weight-huge",
        f"{T} --tracker fused:cotrain_weight=1e308 --box 10,14,14,20",
        r"cotrain_weight must be in \[0, 100\]",
    ),
    E(
        "track-cotrain-motion-huge",
        f"{T} --tracker cotrain:motion_std=1e308 --box 10,14,14,20",
        r"motion_std must be a finite number within \+-1e\+06, got 1e\+308",
    ),
    E(
        "track-histogram-lam-huge",
        f"{T} --tracker histogram:lam=1e308 --box 10,14,14,20",
        r"lam must be a finite number within \+-1e\+06",
    ),
    E(
        "track-multi-confirm-hits-huge",  # no target was ever reported, silently
        "track {c}/frames --tracker multi:confirm_hits=2000000000 -o {o}/b.csv",
        r"confirm_hits must be in \[1, 1000\]",
    ),
    E(
        "track-mil-box-spans-the-frame",  # OpenCV's assertion leaked through
        "track {c}/frames --no-progress --tracker mil --box 0,0,30,48 -o {o}/b.csv",
        "no room around the box to sample positives",
    ),
    E("sign-check-device", "sign --check /dev/null", "is not a regular file"),
    E(
        "track-template-sharpness-nan",
        f"{T} --tracker template:sharpness=nan --box 10,14,14,20",
        "sharpness must be",
    ),
    # the signed model must never land on a key: a private key overwritten is lost for good
    E(
        "sign-out-is-the-key",
        "sign {c}/toy.safetensors --key {c}/alice.pem -o {c}/alice.pem",
        "--out .* is the input --key",
    ),
    E(
        "train-out-is-an-exclude-list",
        f"{TR} --exclude {{c}}/toy.safetensors -o {{c}}/toy.safetensors",
        "--out .* is the input --exclude",
    ),
    E("sign-no-model", "sign --key {c}/alice.pem", "give the MODEL"),
    E(
        "sign-key-missing",
        "sign {c}/toy.safetensors --key {c}/none.pem -o {o}/s.safetensors",
        "cannot be read",
    ),
    E(
        "sign-key-public",
        "sign {c}/toy.safetensors --key {c}/alice.pub -o {o}/s.safetensors",
        "not an unencrypted PEM private key",
    ),
    E(
        "sign-key-junk",
        "sign {c}/toy.safetensors --key {c}/afile -o {o}/s.safetensors",
        "not an unencrypted PEM private key",
    ),
    E("sign-new-key-exists", "sign --new-key {c}/alice.pem", "exists already|never overwritten"),
    E("sign-new-key-parent", "sign --new-key {o}/x/k.pem", "does not exist"),
    E("sign-new-key-dir", "sign --new-key {c}/frames", "is an existing folder"),
    E("sign-new-key-model", "sign {c}/toy.safetensors --new-key {o}/k.pem", "takes no MODEL"),
    E("sign-two-modes", "sign {c}/toy.safetensors --check --key {c}/alice.pem", "exactly one of"),
    E(  # the signed model was written over the public key beside the private one
        "sign-out-not-a-model",
        "sign {c}/toy.safetensors --key {c}/alice.pem -o {o}/alice.pub",
        r"--out '.*alice.pub' must end in .safetensors, got .pub",
    ),
    E(
        "sign-out-dir",
        "sign {c}/toy.safetensors --key {c}/alice.pem -o {c}/frames",
        "is an existing folder",
    ),
    E("sign-check-out", "sign {c}/toy.safetensors --check -o {o}/x.safetensors", "writes nothing"),
    E(
        "sign-forged",
        "sign {c}/forged_threshold.safetensors --key {c}/alice.pem -o {o}/s.safetensors",
        "classifier.threshold",
    ),
    E(
        "sign-forged-signed",
        "sign {c}/forged_signed.safetensors --key {c}/alice.pem -o {o}/s.safetensors",
        "does not verify",
    ),
    E("sign-check-bitflip", "sign --check {c}/bitflip.safetensors", "checksum"),
    E(
        "sign-check-untrusted-required",
        "sign --check {c}/signed.safetensors --require-signed",
        "not trusted here",
    ),
    A(
        "sign-ok",
        "sign {c}/toy.safetensors --key {c}/alice.pem -o {o}/s.safetensors",
        "signed by key",
        ("s.safetensors",),
    ),
    A(
        "sign-check-trusted",
        "sign --check {c}/signed.safetensors --trusted-key {c}/alice.pub",
        "signature verifies",
    ),
    A("sign-new-key", "sign --new-key {o}/k.pem", "key id", ("k.pem", "k.pub")),
    # seeds a torch generator cannot take (were tracebacks), for every command with --seed
    E("seed-huge-track", "track {c}/frames --seed 99999999999999999999999", "--seed: must be", 2),
    E("seed-negative-track", f"track {{c}}/frames {HB} --seed -1", "--seed: must be", 2),
    E(
        "seed-huge-eval",
        "eval --sequences {c}/seqs/good -o {o}/r --seed 18446744073709551616",
        "--seed: must be",
        2,
    ),
    E(
        "seed-huge-train",
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 16 8 "
        "-o {o}/m.safetensors --seed 99999999999999999999999",
        "--seed: must be",
        2,
    ),
    E(
        "seed-huge-calibrate",
        f"{CS} --json {{o}}/p.json --seed 99999999999999999999999",
        "--seed: must be",
        2,
    ),
    # values that were silently taken
    E(
        "train-window-huge",
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 40000 100000 -o {o}/m.safetensors",
        r"sides in \[4, 512\]",
    ),
    E(
        "train-random-negatives-alone",
        # a 16x16 window: a 16x8 one holds no default Haar bank (n_scales 3), refused first
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 16 16 "
        "--random-negatives 100 -o {o}/m.safetensors",
        "--neg-images",
    ),
    E(
        "track-det-min-score-nan",
        "track {c}/frames --detections {c}/det.txt --det-min-score nan -o {o}/b.csv",
        "finite",
    ),
    E(
        "track-spec-key-twice",
        "track {c}/frames --tracker multi:n_particles=10,n_particles=20 -o {o}/b.csv",
        "given twice",
    ),
    E("detect-stride-zero", "detect {c}/toy.safetensors {c}/frames --stride 0", "--stride is"),
    E(
        "detect-scale-step-one",
        "detect {c}/toy.safetensors {c}/frames --scale-step 1",
        "--scale-step must be",
    ),
    E(
        "detect-scan-workers-negative",
        "detect {c}/toy.safetensors {c}/frames --scan-workers -1",
        "--scan-workers must be >= 0",
    ),
    E(
        "detect-scan-workers-too-many",
        "detect {c}/toy.safetensors {c}/frames --scan-workers 100000",
        "more than 4 per CPU core",
    ),
    E("detect-model-is-a-folder", "detect {c}/frames {c}/frames -o {o}/d.jsonl", "is a folder"),
    # the bad-input report: non-UTF-8 files given as text
    E(
        "track-config-binary",
        f"{T} {HB} --config {{c}}/binary.toml",
        "is not valid TOML: not UTF-8",
    ),
    E(  # the cotrain tracker reads its config itself: a UnicodeDecodeError traceback
        "track-cotrain-config-binary",
        f"{T} --box 10,14,14,20 --tracker cotrain --config {{c}}/binary.toml -o {{o}}/b.csv",
        r"bad TOML in .*binary\.toml: not UTF-8 text \(invalid start byte at byte 0\)",
    ),
    E(
        "track-spec-config-binary",
        f"{T} --box 10,14,14,20 --tracker histogram:config={{c}}/binary.toml",
        "is not valid TOML: not UTF-8",
    ),
    E("train-config-binary", "train --config {c}/binary.toml -o {o}/m.safetensors", "not UTF-8"),
    E(
        "train-exclude-binary",
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 16 16 --features 4 "
        "--exclude {c}/toy.safetensors -o {o}/m.safetensors",
        "name list .*toy.safetensors.* not UTF-8",
    ),
    E(
        "track-det-calibration-binary",
        "track {c}/frames --detections {c}/det.txt --det-calibration {c}/toy.safetensors "
        "--mot {o}/m.txt",
        "is not a calibration JSON",
    ),
    *(
        E(
            f"track-det-calibration-{what}",
            f"track {{c}}/frames --detections {{c}}/det.txt --det-calibration {{c}}/cal_{what}.json "
            "--mot {o}/m.txt",
            f"cal_{what}.json' is not a calibration JSON .*{why}",
        )
        for what, why in (("bigint", "Exceeds the limit"), ("deep", "maximum recursion depth"))
    ),
    # calibrations whose probability falls (or stays flat) as the score rises
    E(
        "track-det-calibration-inverted",
        "track {c}/frames --detections {c}/det.txt --det-calibration {c}/cal_inverted.json "
        "--mot {o}/m.txt",
        r"Platt slope A = 1.43 must be in \[-1e\+06, 0\)",
    ),
    E(  # every detection at 0.5 was taken: the flat Platt map was refused, this one not
        "track-det-calibration-isotonic-flat",
        "track {c}/frames --detections {c}/det.txt --det-calibration {c}/cal_iso_flat.json "
        "--mot {o}/m.txt",
        "its isotonic map gives every score the probability 0.5, so it does not rank",
    ),
    E(
        "track-det-calibration-flat",
        "track {c}/frames --detections {c}/det.txt --det-calibration {c}/cal_flat.json "
        "--mot {o}/m.txt",
        "Platt slope A = 0 must be",
    ),
    A(
        "track-det-calibration-ok",
        "track {c}/frames --detections {c}/det.txt --det-calibration {c}/cal_good.json "
        "--mot {o}/m.txt",
        "wrote",
        ("m.txt",),
    ),
    E(
        "cal-scores-inverted",
        "calibrate --scores {c}/inverted.csv --json {o}/p.json --plot {o}/r.png",
        "negatives score higher; are the labels swapped",
    ),
    E(  # the isotonic fit pooled every score into one probability: written, exit 0
        "cal-scores-inverted-isotonic",
        "calibrate --scores {c}/inverted.csv --method isotonic --json {o}/p.json --plot {o}/r.png",
        "isotonic fit gives every score the probability .*, so it does not rank them: .* the "
        "negatives score as high as the positives; are the labels swapped",
    ),
    A(
        "cal-scores-huge",
        "calibrate --scores {c}/huge.csv --json {o}/p.json",
        "did not move from A = 0.*isotonic",
        ("p.json",),
    ),
    A(
        "cal-scores-tiny",  # was silent: a fit blind to the scores
        "calibrate --scores {c}/tiny.csv --json {o}/p.json",
        "did not move from A = 0.*too small for .*underflow",
        ("p.json",),
    ),
    # calibrate MODEL -o OUT --json J writes both
    A(
        "cal-model-out-and-json",
        "calibrate {c}/toy.safetensors --pos {c}/crops/neg --neg {c}/crops/pos -q "
        "-o {o}/m.safetensors --json {o}/c.json",
        "wrote calibration into",
        ("m.safetensors", "c.json"),
    ),
    # non-finite values
    E("detect-max-scale-nan", "detect {c}/toy.safetensors {c}/frames --max-scale nan", "finite"),
    E("detect-max-scale-inf", "detect {c}/toy.safetensors {c}/frames --max-scale inf", "finite"),
    E("detect-min-scale-inf", "detect {c}/toy.safetensors {c}/frames --min-scale inf", "finite"),
    # was refused only after every frame was read and scanned, at 'scale inf (infxinf)'
    E(
        "detect-min-height-inf",
        "detect {c}/toy.safetensors {c}/frames --min-height inf",
        r"--min-height must be > 0 pixels and finite, got inf",
    ),
    # messages that came late or named the wrong thing
    E(
        "train-name-empty",
        "train --pos {c}/crops/pos --neg {c}/crops/neg --window 16 16 --features 4 --name '' "
        "-o {o}/m.safetensors",
        "name must be a string of 1 to 256 characters, got 0 characters",
    ),
    E(
        "track-scan-stride-zero",
        "track {c}/frames --tracker multi:scan_stride=0 -o {o}/b.csv",
        r"scan_stride must be in \(0, 1\]",
    ),
    E("track-tracker-unknown-lists-multi", f"{T} --tracker sift", "known trackers: multi"),
    E("track-multi-with-box", f"{T} --tracker multi --box 10,14,14,20", "takes no --box"),
    # a key set both by an option and by the --tracker spec: one was dropped without a word
    # (or MultiTargetTracker's TypeError 'got multiple values' for config and generator)
    E(
        "track-multi-generator-key",
        f"{T} --tracker multi:generator=1 -o {{o}}/b.csv",
        "'generator' is no key of the multi-target tracker",
    ),
    E(
        "track-multi-scan-every-twice",
        f"{T} --tracker multi:scan_every=2 --scan-every 3 -o {{o}}/b.csv",
        r"--scan-every 3 and --tracker 'multi:scan_every=2' \(scan_every=2\) both set",
    ),
    E(
        "track-multi-model-twice",
        f"{T} --tracker multi:model=vehicle --detect {{c}}/toy.safetensors -o {{o}}/b.csv",
        "--detect .* and --tracker 'multi:model=vehicle' .* both set the tracker's 'model'",
    ),
    E(
        "track-adapt-twice",
        f"{T} --tracker adaptive-haar:adapt=none --adapt global --box 10,14,14,20 -o {{o}}/b.csv",
        "--adapt global and --tracker 'adaptive-haar:adapt=none' .* both set",
    ),
    E(
        "track-detect-twice",
        f"{T} --tracker detector:model=vehicle --detect {{c}}/toy.safetensors --box 10,14,14,20 "
        "-o {o}/b.csv",
        "--detect .* and --tracker 'detector:model=vehicle' .* both set",
    ),
    E(
        "track-frames-below-window",
        "track {c}/tiny --detect {c}/toy.safetensors -o {o}/b.csv",
        "smaller than the detector window 16x8",
    ),
    # a broken symbolic link among the frames: dropped from the listing, every later frame was
    # numbered one too low (track wrote frame 3's box as frame 2; detect --strict passed)
    A(
        "track-broken-link-frame",
        "track {c}/linked --tracker camshift --box 10,14,14,20 --no-progress -o {o}/b.csv",
        "1 unreadable frame",
        ("b.csv",),
    ),
    A(
        "detect-broken-link-frame",
        "detect {c}/toy.safetensors {c}/linked -o {o}/d.jsonl",
        r"skipped frame 2: image .*0002\.png is a broken symbolic link",
        ("d.jsonl",),
    ),
    E(
        "detect-strict-broken-link-frame",
        "detect {c}/toy.safetensors {c}/linked --strict -o {o}/d.jsonl",
        r"0002\.png is a broken symbolic link \(to .*gone\.png, which does not exist\)",
    ),
    # one folder as both classes: the fit learnt only the positive rate, and the model was
    # written with a calibration that ignores its scores (exit 0, a misleading 'underflow' hint)
    E(
        "cal-model-pos-is-neg",
        "calibrate {c}/toy.safetensors --pos {c}/crops/pos --neg {c}/crops/pos/ -o {o}/m.safetensors",
        r"--neg names .*crops/pos/', a folder of --pos: its crops would be both positives and "
        "negatives",
    ),
    E(
        "cal-model-pos-twice",  # every crop counted twice
        "calibrate {c}/toy.safetensors --pos {c}/crops/pos {c}/crops/pos --neg {c}/crops/neg "
        "-o {o}/m.safetensors",
        r"--pos names .*crops/pos' twice",
    ),
    # numbers in a tracker spec as Python reads them, not as a setting is written: 1_0 ran 10
    # particles, Arabic-Indic 50 ran 50, silently
    E(
        "track-spec-number-underscore",
        f"{T} --tracker histogram:n_particles=1_0 --box 10,14,14,20 -o {{o}}/b.csv",
        r"histogram tracker: 'n_particles' must be an integer, got '1_0'",
    ),
    E(
        "track-spec-number-non-ascii",
        f"{T} --tracker histogram:n_particles=\u0665\u0660 --box 10,14,14,20 -o {{o}}/b.csv",
        r"'n_particles' must be an integer, got '\u0665\u0660'",
    ),
    E(
        "eval-spec-number-underscore",
        f"{EV} --trackers camshift:bins=1_6 -o {{o}}/r",
        r"camshift bins must be an integer in \[2, 256\], got '1_6'",
    ),
    # one sequence given twice (or inside a folder also given) was scored twice, weighing
    # double in every overall number, silently
    E(
        "eval-sequence-twice",
        "eval --sequences {c}/seqs/good {c}/seqs/good/ --trackers camshift -o {o}/r",
        r"--sequences gives sequence 'good' \(.*groundtruth_rect\.txt\) twice: through "
        r"'.*seqs/good' and '.*seqs/good/'",
    ),
    E(
        "eval-sequence-in-a-folder-also-given",
        "eval --sequences {c}/seqs {c}/seqs/good --trackers camshift -o {o}/r",
        "--sequences gives sequence 'good' .* twice",
    ),
    # options accepted and silently without effect (the eighth sweep)
    E(
        "track-particles-tracker-without-particles",  # the video had no particle drawn
        "track {c}/frames --no-progress --tracker camshift --box 10,14,14,20 "
        "--video {o}/v.mp4 --particles",
        r"--particles draws a particle filter's particles: tracker 'camshift' has none",
    ),
    # cotrain and template are particle filters too: refused as having no particles (the
    # ninth sweep: they draw them)
    *(
        A(
            f"track-particles-{name}",
            f"track {{c}}/frames --no-progress --tracker {name} --box 10,14,14,20 "
            "--video {o}/v.mp4 --particles",
            "wrote",
            ("v.mp4",),
        )
        for name in ("cotrain", "template")
    ),
    E(
        "eval-mot-results-jobs",  # scored in this process, one after another
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt --jobs 2 -o {o}/r",
        r"--jobs do\(es\) not apply to scoring existing results files \(--mot with --results\)$",
    ),
    E(
        "eval-mot-results-seed",  # nothing random in scoring; recorded in results.json as used
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt --seed 3 -o {o}/r",
        r"--seed do\(es\) not apply to scoring existing results files",
    ),
    E(
        "eval-mot-results-invisible",
        "eval --mot {c}/mot/TOY-01 --results {c}/res.txt --invisible miss -o {o}/r",
        r"--invisible do\(es\) not apply",
    ),
    E(
        "eval-mot-trackers-on-mismatch",
        "eval --mot {c}/mot/TOY-01 --trackers multi --on-mismatch truncate -o {o}/r",
        r"--on-mismatch do\(es\) not apply to --mot",
    ),
    E(
        "eval-mot-trackers-backend",
        "eval --mot {c}/mot/TOY-01 --trackers multi --backend ray --max-retries 1 -o {o}/r",
        r"--backend, --max-retries do\(es\) not apply to --mot",
    ),
    E(
        "cal-scores-region",  # the crop region of a score file: nothing to cut
        f"{CS} --json {{o}}/p.json --region 0 0 8 8 --crop-size 16 16",
        r"--region, --crop-size go\(es\) with a MODEL's --pos / --neg crops, not with --scores",
    ),
    E("cal-scores-strict", f"{CS} --json {{o}}/p.json --strict", "--strict go"),
    E(
        "train-variant-with-svm",  # the SVM was trained; the variant went nowhere
        f"{TR} --classifier svm --variant real -o {{o}}/m.safetensors",
        r"learn.variant = 'real' is the boosting variant: learn.classifier = 'svm'",
    ),
    E(
        "detect-cascade-haar-model",  # a Haar model has no soft cascade: the scan ignored it
        f"{D} --cascade -5 -o {{o}}/d.jsonl",
        r"--cascade sets the soft cascade of channel models .* has none",
    ),
    E("detect-no-cascade-haar-model", f"{D} --no-cascade -o {{o}}/d.jsonl", "--no-cascade sets"),
    A(
        "eval-mot-gt-conf-fractional",  # every row ignored by the scoring, and no word of it
        "eval --mot {c}/mot/HALF --results {c}/res.txt",
        r"6 ground-truth row\(s\) of TOY-01 .* have a conf in \(0, 1\): .* so they are ignored",
    ),
    # signing wrote the file, then refused it as untrusted: exit 1 with the output left
    E(
        "sign-require-signed",
        "sign {c}/toy.safetensors --key {c}/alice.pem -o {o}/s.safetensors --require-signed",
        r"--require-signed decide\(s\) which model files are accepted: they go with --check",
    ),
    E(
        "sign-trusted-key-other-signer",
        "sign {c}/toy.safetensors --key {c}/alice.pem -o {o}/s.safetensors "
        "--trusted-key {c}/mallory.pub",
        "--trusted-key decide",
    ),
    E("sign-new-key-trusted-key", "sign --new-key {o}/k.pem --trusted-key {c}/alice.pub", "decide"),
    # frames resized since the ground truth was drawn: scored against boxes 10x their size,
    # the warnings measuring the frames by seqinfo.ini (exit 0, every box a miss)
    E(
        "eval-mot-frames-not-seqinfo-size",
        "eval --mot {c}/mot/RESIZED --results {c}/res.txt -o {o}/r",
        r"img1/0000\.jpg is 64x48 but .*RESIZED/seqinfo\.ini says imWidth=640 imHeight=480",
    ),
    A(
        "eval-mot-frames-not-seqinfo-size-scale-given",
        "eval --mot {c}/mot/RESIZED --results {c}/res.txt --gt-scale 1",
        "HOTA",
    ),
    E(
        "detect-vote-without-nms",  # the scan votes only among what NMS keeps: dropped, silently
        f"{D} --vote-iou 0.7 --nms-iou 1 -o {{o}}/d.jsonl",
        r"--vote-iou 0.7 refines .* with --nms-iou 1 \(off\) there is none",
    ),
    # sizes of a single-target tracker's tensors and loops (the ninth sweep): 10^9 particles
    # was torch's allocation error as a traceback, 10^9 co-training passes ran for ever
    E(
        "track-single-particles-huge",
        f"{T} --tracker histogram:n_particles=1000000000 --box 10,14,14,20 -o {{o}}/b.csv",
        r"histogram tracker: n_particles must be in \[1, 100000\], got 1000000000$",
    ),
    E(
        "track-template-size-huge",
        f"{T} --tracker template:template_size=1000000000 --box 10,14,14,20 -o {{o}}/b.csv",
        r"n_particles x template_size\^2 = 400 x 1000000000\^2 is more than 33554432 warped",
    ),
    E(
        "track-cotrain-passes-huge",
        f"{T} --tracker cotrain:init_passes=1000000000 --box 10,14,14,20 -o {{o}}/b.csv",
        r"cotrain: init_passes must be in \[1, 100\], got 1000000000",
    ),
    E(
        "train-haar-stride-beyond-window",  # once trained to the end, then 'not writing ...'
        "train --config {c}/haar_stride.toml -q -o {o}/m.safetensors",
        r"features\.stride must be an integer in \[1, 16\], got 17 \(a Haar bank no model "
        "file may hold\\)",
    ),
    # seqinfo.ini (the ninth sweep)
    E(
        "eval-mot-seqinfo-frame-rate-inf",
        "eval --mot {c}/mot/RATEINF --results {c}/res.txt -o {o}/r",
        r"RATEINF/seqinfo\.ini: frameRate='inf' must be a finite number > 0",
    ),
    A(
        "eval-mot-seqinfo-length-with-a-point",  # was 'not a number'
        "eval --mot {c}/mot/LENFLOAT --results {c}/res.txt -o {o}/r",
        "HOTA",
        ("r/results.json", "r/results.md"),
    ),
    E(
        "eval-mot-seqinfo-imext-not-the-frames",  # imExt was ignored
        "eval --mot {c}/mot/PNGEXT --results {c}/res.txt -o {o}/r",
        r"PNGEXT/img1 holds no \.png frame \(the extension .*seqinfo\.ini gives, imExt=\.png\): "
        r"it holds 6 \.jpg file\(s\)",
    ),
    # a header naming the score column and not the label column (or the other way round)
    E(
        "cal-scores-header-without-label",
        "calibrate --scores {c}/nolabel.csv --json {o}/p.json",
        r"score file '.*nolabel\.csv': its header 'frame,score,y' names column 2 'score' and no "
        r"column 'label', so the first two columns would be read as score, label",
    ),
    E(
        "cal-scores-header-without-score",
        "calibrate --scores {c}/noscore.csv --json {o}/p.json",
        r"noscore\.csv': its header 'label,margin' names column 1 'label' and no column 'score'",
    ),
    A(
        "cal-scores-header-label-only",  # margin,label: read by position, as named
        "calibrate --scores {c}/labelonly.csv --json {o}/p.json",
        "wrote",
        ("p.json",),
    ),
    # the top level
    E("top-unknown-command", "frobnicate", "invalid choice", 2),
    E("top-no-command", "", "usage", 2),
]


def _cannot_create_in(folder: str) -> bool:
    import tempfile

    try:
        fd, probe = tempfile.mkstemp(dir=folder)
    except OSError:
        return True
    os.close(fd)
    os.unlink(probe)
    return False


# Outputs in a folder that exists but takes no new file (/proc, even for root, who passes
# every permission check): refused before any work, never a traceback after it.
if os.path.isdir("/proc") and _cannot_create_in("/proc"):
    NO = "folder '/proc' is not writable"
    CASES += [
        E("proc-track-out", f"{T} {HB} -o /proc/x.csv", NO),
        E("proc-track-mot", "track {c}/frames --detections {c}/det.txt --mot /proc/x.txt", NO),
        E("proc-track-video", f"{T} {HB} -o {{o}}/b.csv --video /proc/x.mp4", NO),
        E("proc-detect-out", "detect {c}/toy.safetensors {c}/frames -o /proc/x.jsonl", NO),
        E("proc-detect-video", "detect {c}/toy.safetensors {c}/frames --video /proc/x.mp4", NO),
        E(
            "proc-detect-annotate",
            "detect {c}/toy.safetensors {c}/frames -o {o}/d.jsonl --annotate /proc/xdir",
            NO,
        ),
        E("proc-cal-json", f"{CS} --json /proc/c.json", NO),
        E("proc-cal-plot", f"{CS} --json {{o}}/c.json --plot /proc/p.png", NO),
        E("proc-cal-model-plot", f"{CM} -o {{o}}/m.safetensors --plot /proc/p.png", NO),
        E(
            "proc-train-out",
            "train --pos {c}/crops/pos --neg {c}/crops/neg --window 16 16 --features 4 "
            "-o /proc/m.safetensors",
            NO,
        ),
        E(
            "proc-sign-out",
            "sign {c}/toy.safetensors --key {c}/alice.pem -o /proc/s.safetensors",
            NO,
        ),
        E("proc-sign-new-key", "sign --new-key /proc/k.pem", NO),
    ]


def _fill(argv: tuple[str, ...], c: Path, o: Path) -> list[str]:
    return [a.replace("{c}", str(c)).replace("{o}", str(o)) for a in argv]


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}


@pytest.fixture(autouse=True)
def _restore_threads():
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)


def test_corpus_is_large_and_named_uniquely():
    ids = [c.id for c in CASES]
    assert len(ids) == len(set(ids)) and len(ids) >= 200, len(ids)


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.id)
@pytest.mark.filterwarnings("ignore:sequence short")
def test_bad_input(case: Case, corpus, tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    before = _files(corpus)
    try:
        code = main(_fill(case.argv, corpus, out))
    except SystemExit as exc:  # argparse: usage errors exit 2 with a message
        code = exc.code
    captured = capsys.readouterr()
    text = captured.err if case.code else captured.out + captured.err
    assert code == case.code, f"exit {code}, expected {case.code}; stderr: {captured.err[-800:]}"
    assert re.search(case.match, text), f"{case.match!r} not in: {text[-800:]}"
    assert "Traceback" not in captured.err
    assert _files(out) == set(case.keep), "a failed run left output behind" if case.code else ""
    # nothing written beside the inputs either (temporary files, .part files, plots)
    assert _files(corpus) == before


# ------------------------------------------------------------------- cases on real data
def test_real_truncated_frame_and_video(data_dir, tmp_path, capsys):
    """The issue's cases on shared data: a BoBoT frame cut to 25% of its bytes is counted as
    unreadable by track (and caught by detect --strict); the PETS clip cut in half makes
    detect warn that it ended early."""
    src = data_dir / "tracking" / "bobot_pedestrian" / "frames"
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2, 7):
        (frames / f"img{i:04d}.jpg").write_bytes((src / f"img{i:04d}.jpg").read_bytes())
    cut = frames / "img0004.jpg"
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 4])
    out = tmp_path / "b.csv"
    argv = ["track", str(frames), "--tracker", "camshift", "--box", "108,47,56,156"]
    assert main([*argv, "-o", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr()
    assert "1 unreadable frame(s)" in printed.out
    rows = out.read_text().splitlines()[1:]
    assert rows[2].endswith(",0") and len(rows) == 5  # the cut frame: not visible
    assert (
        main(["detect", "pedestrian", str(frames), "--strict", "-q", "-o", str(tmp_path / "d")])
        == 1
    )
    assert "img0004.jpg is truncated" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
    video = data_dir / "videos" / "pets2009_s2l1_vtest" / "vtest.avi"
    if video.is_file():
        data = video.read_bytes()
        short = tmp_path / "short.avi"
        short.write_bytes(data[: len(data) // 40])
        code = main(
            [
                "detect",
                "pedestrian",
                str(short),
                "--max-frames",
                "400",
                "--no-progress",
                "--min-scale",
                "2",
                "-o",
                str(tmp_path / "d.jsonl"),
            ]
        )
        err = capsys.readouterr().err
        assert code == 0 and "ended early" in err and "Traceback" not in err


def test_sigterm_finishes_the_csv_like_sigint(corpus, tmp_path, capsys):
    """SIGTERM during tracking: the rows so far are kept and OUT is a finished file (no
    .part left), exit status 143."""
    import signal
    import threading

    from torchtrack.track import base

    out = tmp_path / "b.csv"
    real_update = base.Tracker.update
    calls = {"n": 0}

    def update(self, frame):
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return real_update(self, frame)

    assert threading.current_thread() is threading.main_thread()
    base.Tracker.update = update
    try:
        code = main(["track", str(corpus / "frames"), *HB.split(), "-o", str(out), "--no-progress"])
    finally:
        base.Tracker.update = real_update
    assert code == 143
    assert "terminated: keeping the results so far" in capsys.readouterr().err
    assert out.is_file() and not (tmp_path / "b.csv.part").exists()
    assert len(out.read_text().splitlines()) >= 3  # header + the frames before the signal
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored after the command


def test_model_header_is_not_allocated(corpus):
    """The forged 100000 x 100000 window is refused from the header (struct + JSON only)."""
    from torchtrack.detect import load_detector
    from torchtrack.errors import ModelFormatError

    data = (corpus / "forged_bankwin.safetensors").read_bytes()
    (n,) = struct.unpack("<Q", data[:8])
    meta = json.loads(json.loads(data[8 : 8 + n])["__metadata__"]["torchtrack"])
    assert meta["window"] == [100000, 100000]
    with pytest.raises(ModelFormatError, match="window height"):
        load_detector(corpus / "forged_bankwin.safetensors")


@pytest.mark.parametrize(
    "argv",
    [
        "track {c}/cut.mp4 --tracker camshift --box 1,1,9,9 -o {o}/b.csv",
        "track {c}/badcrops --tracker camshift --box 1,1,9,9 -o {o}/b.csv",
        "detect {c}/toy.safetensors {c}/badcrops -o {o}/d.jsonl",
        "detect {c}/toy.safetensors {c}/jpgs --strict -o {o}/d.jsonl",
        "detect {c}/toy.safetensors {c}/text.mp4 -o {o}/d.jsonl",
        # configparser's messages span lines: the file's line and its text came on two more
        "eval --mot {c}/mot/NOHEADER --results {c}/res.txt -o {o}/r",
        "eval --mot {c}/mot/GARBAGE --results {c}/res.txt -o {o}/r",
    ],
)
def test_one_clean_line_and_no_library_noise(argv, corpus, tmp_path, capfd):
    """What libjpeg, libpng, FFmpeg and OpenCV print goes into the error message (or nowhere),
    not onto the terminal before it; an open progress bar is closed first, so the error
    starts a line of its own."""
    out = tmp_path / "o"
    out.mkdir()
    assert main(_fill(tuple(_split(argv)), corpus, out)) == 1
    err = capfd.readouterr().err
    lines = [ln for ln in re.split(r"[\r\n]", err) if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("torchtrack ")]
    assert len(errors) == 1, err
    noise = [ln for ln in lines if not ln.startswith(("torchtrack ", "detect:", "  "))]
    noise = [ln for ln in noise if "frame/s" not in ln and "it/s" not in ln]
    assert noise == [], err
    assert _files(out) == set()


@pytest.mark.parametrize(
    "argv",
    [
        "track {i}/frames --detections {i}/det.txt --mot {i}/det.txt",
        "track {i}/frames --tracker camshift --box 1,1,9,9 -o {i}/frames/0000.png",
        "track {i}/frames --config {i}/multi.toml -o {i}/multi.toml",
        "track {i}/frames --detect {i}/toy.safetensors -o {i}/toy.safetensors",
        "detect {i}/toy.safetensors {i}/frames -o {i}/toy.safetensors",
        "detect {i}/toy.safetensors {i}/frames -o {o}/d.jsonl --annotate {i}/frames",
        "detect {i}/toy.safetensors {i}/frames -o {o}/d.jsonl --annotate {i}/frames/ann",
        "train --pos {i}/crops/pos --neg {i}/crops/neg --window 16 8 --features 5 "
        "-o {i}/crops/pos/m.safetensors",
        "calibrate {i}/toy.safetensors --pos {i}/crops/pos --neg {i}/crops/neg "
        "-o {i}/crops/pos/pos-0.png",
    ],
)
def test_outputs_never_overwrite_or_join_the_inputs(argv, corpus, tmp_path, capsys):
    """An output that is an input file (detections, config, model, a frame, a crop) or lies
    inside an input folder is refused before any work, naming both; every input is intact."""
    import shutil

    inp, out = tmp_path / "in", tmp_path / "out"
    out.mkdir()
    shutil.copytree(corpus / "frames", inp / "frames")
    shutil.copytree(corpus / "crops", inp / "crops")
    shutil.copy(corpus / "toy.safetensors", inp)
    (inp / "det.txt").write_text("1,-1,2,2,8,16,0.9,-1,-1,-1\n")
    (inp / "multi.toml").write_text("max_targets = 5\n")
    before = {p: (inp / p).read_bytes() for p in _files(inp)}
    argv = [a.replace("{i}", str(inp)).replace("{o}", str(out)) for a in _split(argv)]
    assert main([*argv, "-q" if argv[0] != "train" else "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "write the output elsewhere" in err and "Traceback" not in err, err
    assert {p: (inp / p).read_bytes() for p in _files(inp)} == before
    assert _files(out) == set()


def test_detect_that_fails_midway_leaves_no_annotated_frames(corpus, tmp_path, capsys):
    """A folder whose last image is too small for the window fails under --strict after the
    other frames were annotated: those annotated frames go with the rest of the output."""
    import shutil

    import cv2
    import numpy as np

    frames = tmp_path / "frames"
    shutil.copytree(corpus / "frames", frames)
    cv2.imwrite(str(frames / "zzzz.png"), np.zeros((4, 4, 3), np.uint8))  # last, too small
    ann, out = tmp_path / "ann", tmp_path / "d.jsonl"
    argv = ["detect", str(corpus / "toy.safetensors"), str(frames), "--strict", "--batch", "1"]
    assert main([*argv, "-o", str(out), "--annotate", str(ann), "-q"]) == 1
    assert "Traceback" not in capsys.readouterr().err
    assert not ann.exists() and not out.exists()


def test_detect_gives_each_reason_for_no_frame_once(corpus, tmp_path, capsys):
    """Three 1x1 frames, each too small for the window for the same reason: the error said it
    three times over; frames of different reasons (undecodable files) each keep theirs."""
    assert main(["detect", str(corpus / "toy.safetensors"), str(corpus / "tiny")]) == 1
    err = capsys.readouterr().err
    assert err.count("is smaller than the detector window") == 1, err
    assert main(["detect", str(corpus / "toy.safetensors"), str(corpus / "corrupt")]) == 1
    assert capsys.readouterr().err.count("cannot be decoded") == 3


def test_failed_detect_keeps_an_earlier_runs_annotated_frames(corpus, tmp_path, capsys):
    """The same --annotate DIR again, and this run fails after annotating the first frames:
    the earlier run's annotated frames stay as they were (they were all deleted, while its
    --out JSON lines were kept)."""
    import shutil

    frames = tmp_path / "frames"
    shutil.copytree(corpus / "frames", frames)
    ann, out = tmp_path / "ann", tmp_path / "d.jsonl"
    argv = ["detect", str(corpus / "toy.safetensors"), str(frames), "--batch", "1", "-q"]
    assert main([*argv, "--threshold", "0.9", "-o", str(out), "--annotate", str(ann)]) == 0
    before = {p.name: p.read_bytes() for p in ann.iterdir()}
    assert len(before) == 6
    cv2.imwrite(str(frames / "zzzz.png"), np.zeros((4, 4, 3), np.uint8))  # last, too small
    assert main([*argv, "--strict", "-o", str(out), "--annotate", str(ann)]) == 1
    assert "Traceback" not in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in ann.iterdir()} == before  # no temporary file either


def test_warnings_print_as_one_line_like_errors():
    """A library warning under the CLI reads `torchtrack COMMAND: warning: ...`, without the
    warning class, the module's path and its code line; the format is restored afterwards."""
    import warnings

    from torchtrack.cli import _plain_warnings

    before = warnings.formatwarning
    with _plain_warnings("eval"):
        text = warnings.formatwarning("sequence X: 240 rows", UserWarning, "/a/b/io.py", 413)
    assert text == "torchtrack eval: warning: sequence X: 240 rows\n"
    assert warnings.formatwarning is before


def test_detections_mostly_outside_the_frames_warn(corpus, tmp_path):
    """Boxes that only partly fit the frames (another video's, or in other units) are tracked
    with a warning that says so, not silently turned into empty tracks."""
    argv = _fill(
        tuple(_split(f"{MT} --detections {{c}}/det_tall.txt --mot {{o}}/m.txt")), corpus, tmp_path
    )
    with pytest.warns(UserWarning, match="6 of the 6 boxes .* lie mostly outside the 64x48 frames"):
        assert main(argv) == 0


def test_signing_under_required_signatures_reports_the_signer(corpus, tmp_path, monkeypatch):
    """TORCHTRACK_REQUIRE_SIGNED=1 in the environment: the signed file was written, then
    refused as signed by an untrusted key (exit 1, the file left). The report now only says
    who signed it."""
    from torchtrack.detect.signing import ENV_REQUIRE

    monkeypatch.setenv(ENV_REQUIRE, "1")
    out = tmp_path / "s.safetensors"
    key = str(corpus / "alice.pem")
    assert main(["sign", str(corpus / "toy.safetensors"), "--key", key, "-o", str(out)]) == 0
    assert out.is_file()


def test_signing_a_bundled_model_by_name_needs_an_out(corpus, tmp_path, monkeypatch, capsys):
    """`sign NAME --key PEM` with a bundled model's name signed the installed model file in
    place with the user's key (calibrate refuses to rewrite it): now a ConfigError asking for
    -o; with -o the signed copy is written and the installed file is left as it was."""
    import shutil

    import torchtrack.detect.bundled as bundled

    models = tmp_path / "models"
    models.mkdir()
    shutil.copy(corpus / "toy.safetensors", models / "toy.safetensors")
    monkeypatch.setattr(bundled, "MODELS_DIR", models)
    monkeypatch.chdir(tmp_path)  # 'toy' names no file here
    before = (models / "toy.safetensors").read_bytes()
    key = str(corpus / "alice.pem")
    assert main(["sign", "toy", "--key", key]) == 1
    assert "MODEL 'toy' is a bundled model: give -o OUT" in capsys.readouterr().err
    assert (models / "toy.safetensors").read_bytes() == before
    assert main(["sign", "toy", "--key", key, "-o", str(tmp_path / "s.safetensors")]) == 0
    assert (tmp_path / "s.safetensors").is_file()
    assert (models / "toy.safetensors").read_bytes() == before
