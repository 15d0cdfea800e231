"""Choose multi-target defaults by leave-one-sequence-out, over seeds (``MultiTargetTracker``).

Every candidate setting of one key (``--grid key=v1,v2,...``, the others at their defaults)
tracks every setting below for every seed; TrackEval scores each run (MOT15 conventions). The
candidates are then judged the way the defaults are chosen (docs/multi_target.md):

* **own**: the bundled model's own detections, scanned once per sequence at the tracker's scan
  settings and cached under ``--cache`` (the same boxes and probabilities the tracker's scan
  gives), on PETS09-S2L1 and TUD-Stadtmitte. Leave one sequence out: the value that is best on
  one sequence, scored on the other, is the honest estimate of what the choice is worth on a
  sequence nobody tuned on. The cache is a MOT file, its probabilities written to 6 significant
  digits: a probability above 0.9999995 reads back as 1, so a grid over `birth_threshold`
  values above 0.999999 (or a model surer than that of its best windows, whose video level
  `birth_floor` reads) is resolved only by `--live` runs.
* **outside detections**, a check that the choice is not specific to our detector: the MOT15
  public detections of TUD-Stadtmitte (scores divided by their largest, as the CLI does) and
  the ground-truth boxes with 10% dropped and 2 px jitter (the tracker's ceiling; the same
  draw as ``tools/bench_mot.py``'s ``GT + ByteTrack`` rows) on both sequences.

Usage::

    python tools/loso_multi.py --grid motion_noise=1,0.5,0.25,0.1 --seeds 0,1,2,3
    python tools/loso_multi.py --grid overlap_gate=0.1,0.3 --settings own:PETS09-S2L1,public:TUD-Stadtmitte

With ``--degrade contrast=0.5,noise=8`` every sequence is replaced by a copy whose contrast is
lowered about mid-grey and to which sensor noise (a fresh Gaussian draw per frame, seeded by the
frame's index) is added, written once as a MOTChallenge folder under ``--cache``: video on
which the detector is less sure of everyone, as on footage unlike its training crops (a check
of adaptive births, ``birth_floor``). ``gray=1`` makes the frames grey first (a
monochrome camera); ``gain=A`` then multiplies the brightness of frame t by
``1 + A sin(2 pi t / P)`` (``period=P``, default 100 frames): light that changes over the video.

    python tools/loso_multi.py --grid birth_floor=0.9999,0.995 --degrade contrast=0.5,noise=8

With ``--rescale S`` every sequence is replaced by a copy resized by S (its ground truth and
public detections scaled with it): the same people at another resolution, a check that a
setting in pixels does not hold only at the two clips' own size.

    python tools/loso_multi.py --grid noise_height=0,120 --rescale 2

``--every K`` keeps every K-th frame (ground truth and public detections with them): the same
people at a K times lower frame rate, a check of the settings counted in frames.

    python tools/loso_multi.py --grid max_lost=30 --every 3

``--pan V`` crops every frame to a window 3/4 of its width that slides right and back at V px
a frame (ground truth and public detections shifted with it): the same people seen by a
panning camera, a check of the motion model and of ``camera_motion``.

    python tools/loso_multi.py --grid camera_motion=false,true --pan 3

``--shake A`` crops every frame to a window 2A px narrower and shorter at a random offset
(up to 2A px on both axes, drawn afresh each frame): a shaking hand-held camera.

    python tools/loso_multi.py --grid camera_motion=false,true --shake 4

``--zoom R`` magnifies every frame about the horizon (the row the ground truth's people give)
by ``1 + R`` a frame up to 1.5x and back, resized to the frame's size (ground truth and public
detections scaled with it): a camera walking towards the scene and back, whose people grow,
shrink and move away from the horizon's centre (scale and motion beyond a translation).

    python tools/loso_multi.py --grid camera_motion=false,true --zoom 0.01

``--set key=v,...`` holds other keys at those values for every candidate (a grid on top of a
non-default setting).

``--live N``: the own-detection runs scan every frame themselves, as ``torchtrack track``
does (once the video's ground plane is learnt, each scan scores only the windows that fit it,
with ``N`` processes scanning ahead), instead of reading the cache. The cache holds full scans
whose off-plane detections the tracker drops afterwards, with boxes and probabilities rounded:
close to the command, not the same, and identities swing with such differences. On
2026-11-28 the two disagreed on a change (docs/multi_target.md, the explained-away term): the
cached scans for quick screening, ``--live`` for the choice. About 1-2 minutes per PETS run.

    python tools/loso_multi.py --grid duplicate_iou=0.6,0.85 --live 2 --settings own:PETS09-S2L1,own:TUD-Stadtmitte

Prints a markdown table: HOTA mean ± sd over seeds (MOTA and IDF1 means beside), then the
leave-one-sequence-out line. Nothing is timed.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from torchtrack.detect.bundled import resolve_model  # noqa: E402
from torchtrack.detect.model_file import read_model_metadata  # noqa: E402
from torchtrack.errors import ConfigError  # noqa: E402
from torchtrack.eval.mot import gt_as_detections, score_mot  # noqa: E402
from torchtrack.io.mot import (  # noqa: E402
    MotRows,
    MotSequence,
    load_mot_sequence,
    read_mot,
    write_mot,
)
from torchtrack.track.base import parse_tracker_spec  # noqa: E402
from torchtrack.track.config import MultiTrackerConfig, apply_overrides  # noqa: E402
from torchtrack.track.multi import (  # noqa: E402
    MultiTargetTracker,
    score_probabilities,
    track_sequence,
)

SEQUENCES = ("PETS09-S2L1", "TUD-Stadtmitte")
KINDS = ("own", "public", "gt")


def load(data: Path, name: str) -> MotSequence:
    if name == "PETS09-S2L1":  # the shared 480x360 video, GT x0.625 (seqinfo.ini)
        return load_mot_sequence(
            data / "videos" / "pets2009_s2l1_vtest" / "vtest.avi",
            gt=data / "mot" / "PETS09-S2L1" / "gt" / "gt.txt",
        )
    return load_mot_sequence(data / "mot" / name)


def degrade(
    frame: np.ndarray,
    contrast: float,
    noise: float,
    index: int,
    gray: bool = False,
    gain: float = 0.0,
    period: float = 100.0,
    blur: float = 0.0,
    jpeg: int = 0,
) -> np.ndarray:
    """``(H, W, C)`` uint8 with its contrast scaled by ``contrast`` about 128 and Gaussian
    noise of sd ``noise`` (grey levels) added, the draw seeded by ``index``; with ``gray``
    first made grey (ITU-R 601 luma in all three channels: a monochrome camera); with ``gain``
    its brightness then multiplied by ``1 + gain sin(2 pi index / period)`` (light that changes
    over the video, as ``tools/make_copies.py --gain`` does to single-target sequences); with
    ``blur`` first blurred by a Gaussian of that sd in pixels (a soft lens, focus or motion);
    with ``jpeg`` last compressed as a JPEG of that quality (1-100: a low-bitrate camera)."""
    import cv2

    if blur > 0:
        frame = cv2.GaussianBlur(frame, (0, 0), blur)
    out = frame.astype(np.float32)
    if gray:
        luma = out @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        out = np.repeat(luma[..., None], frame.shape[-1], -1)
    out = (out - 128.0) * contrast + 128.0
    if gain:
        out *= 1.0 + gain * math.sin(2.0 * math.pi * index / period)
    if noise > 0:
        out += np.random.default_rng(index).normal(0.0, noise, frame.shape).astype(np.float32)
    out = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    if jpeg:
        _, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg)])
        out = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).reshape(out.shape)
    return out


def degraded(seq: MotSequence, spec: str, cache: Path) -> MotSequence:
    """``seq`` through :func:`degrade` (``spec``:
    ``contrast=C,noise=S[,gray=1][,gain=A[,period=P]][,blur=B][,jpeg=Q]``), written once as a
    MOTChallenge folder (PNG frames, the ground truth in their pixels) under ``cache``."""
    usage = "contrast=C,noise=S[,gray=1][,gain=A[,period=P]][,blur=B][,jpeg=Q]"
    try:
        kv = dict(item.split("=") for item in spec.split(","))
        contrast, noise = float(kv.pop("contrast", 1.0)), float(kv.pop("noise", 0.0))
        gray = bool(int(kv.pop("gray", 0)))
        gain, period = float(kv.pop("gain", 0.0)), float(kv.pop("period", 100.0))
        blur, jpeg = float(kv.pop("blur", 0.0)), int(kv.pop("jpeg", 0))
    except ValueError:
        raise SystemExit(f"--degrade: expected {usage}, got {spec!r}") from None
    if kv or not (
        0 < contrast <= 1
        and noise >= 0
        and 0 <= gain < 1
        and period > 0
        and 0 <= blur <= 20
        and 0 <= jpeg <= 100
    ):
        raise SystemExit(
            f"--degrade: expected contrast in (0, 1], noise >= 0, gain in [0, 1), period > 0, "
            f"blur in [0, 20] px and jpeg in [0, 100] ({usage}), got {spec!r}"
        )
    name = f"{seq.name}-c{contrast:g}-n{noise:g}{'-gray' if gray else ''}"
    if gain:
        name += f"-gain{gain:g}-p{period:g}"
    if blur:
        name += f"-blur{blur:g}"
    if jpeg:
        name += f"-jpeg{jpeg}"
    return _copy(
        seq, name, cache / "degraded",
        lambda img, i: degrade(img, contrast, noise, i, gray, gain, period, blur, jpeg),
    )  # fmt: skip


def rescaled(seq: MotSequence, scale: float, cache: Path) -> MotSequence:
    """``seq`` with every frame resized by ``scale`` (area averaging down, bilinear up) and its
    ground truth and public detections scaled with it: the same people, nearer or farther in
    pixels (a check that a default does not hold only at the clips' own resolution)."""
    import cv2

    if not scale > 0:
        raise SystemExit(f"--rescale must be > 0, got {scale}")
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return _copy(
        seq, f"{seq.name}-x{scale:g}", cache / "rescaled",
        lambda img, i: cv2.resize(img, None, fx=scale, fy=scale, interpolation=interp),
        box_scale=scale,
    )  # fmt: skip


def subsampled(seq: MotSequence, every: int, cache: Path) -> MotSequence:
    """``seq`` keeping every ``every``-th frame (its ground truth and public detections with
    it): the same people at a lower frame rate, each moving ``every`` times as far between
    frames (a check that a setting in frames does not hold only at the clips' own rate)."""
    if every < 1:
        raise SystemExit(f"--every must be >= 1, got {every}")
    return _copy(seq, f"{seq.name}-every{every}", cache / "subsampled", lambda img, i: img,
                 every=every)  # fmt: skip


def panned(seq: MotSequence, speed: float, cache: Path) -> MotSequence:
    """``seq`` seen by a camera that pans: every frame cropped to a window 3/4 of its width
    that slides right and back (a triangle wave over the frame's last quarter) at ``speed``
    pixels a frame, so the whole scene moves ``speed`` pixels a frame the other way; ground
    truth and public detections shifted with it, those less than half inside dropped."""
    if not speed > 0:
        raise SystemExit(f"--pan must be > 0, got {speed}")
    span = seq.width // 4

    def offset(i: int) -> tuple[int, int]:
        p = (speed * i) % (2 * span)
        return round(p if p <= span else 2 * span - p), 0

    return _crop_copy(seq, f"{seq.name}-pan{speed:g}", cache / "panned", offset, span, 0)


def shaken(seq: MotSequence, amplitude: int, cache: Path) -> MotSequence:
    """``seq`` seen by a shaking hand-held camera: every frame cropped to a window
    ``2 * amplitude`` pixels narrower and shorter, at an offset drawn afresh each frame
    (uniform in [0, 2 amplitude] on both axes, seeded by the frame's index); ground truth and
    public detections shifted with it, those less than half inside dropped."""
    if not amplitude >= 1:
        raise SystemExit(f"--shake must be >= 1 pixel, got {amplitude}")

    def offset(i: int) -> tuple[int, int]:
        dx, dy = np.random.default_rng(i).integers(0, 2 * amplitude + 1, 2)
        return int(dx), int(dy)

    return _crop_copy(
        seq, f"{seq.name}-shake{amplitude}", cache / "shaken", offset, 2 * amplitude,
        2 * amplitude,
    )  # fmt: skip


def zoomed(seq: MotSequence, rate: float, cache: Path, top: float = 1.5) -> MotSequence:
    """``seq`` seen by a camera that moves towards the scene and back: frame i is the window
    ``1 / z(i)`` of the frame's size about an anchor point, resized back to the frame's size,
    where the magnification ``z`` grows by ``1 + rate`` a frame up to ``top`` and shrinks back
    (a triangle wave in log z). The anchor is the column of the frame's centre on the row of
    the horizon that the ground truth's people give (the foot row where their fitted height
    reaches 0; the top row when that lies above the frame): a zoom about the horizon keeps a
    person's height proportional to its foot row's distance from it, as a camera walking
    forward on flat ground does. Ground truth and public detections scaled with it, those
    less than half inside dropped."""
    if not rate > 0:
        raise SystemExit(f"--zoom must be > 0, got {rate}")
    g = seq.gt.boxes
    a, b = np.polyfit(g[:, 1] + g[:, 3], g[:, 3], 1)  # height = a foot + b, every person
    ay = float(np.clip(-b / a if a > 0 else 0.0, 0.0, seq.height - 1.0))
    transform = zoom_transform(seq.width / 2.0, ay, rate, top)
    return _copy(
        seq, f"{seq.name}-zoom{rate:g}", cache / "zoomed",
        lambda img, i: zoom_warp(img, *transform(i)),
        box_shift=(transform, seq.width, seq.height),
    )  # fmt: skip


def zoom_transform(ax: float, ay: float, rate: float, top: float):
    """``transform(i) -> (x0, y0, z)``: frame i of a zoom about ``(ax, ay)`` shows the window
    whose top-left corner is ``(x0, y0)`` magnified ``z`` times, ``z`` growing by ``1 + rate``
    a frame from 1 to ``top`` and back (a triangle wave in log z); a point ``p`` of the frame
    is then seen at ``z (p - (x0, y0)) = z (p - a) + a``."""
    half = math.log(top) / math.log1p(rate)  # frames from 1 to top

    def transform(i: int) -> tuple[float, float, float]:
        p = i % (2 * half)
        z = math.exp(math.log1p(rate) * (p if p <= half else 2 * half - p))
        return ax * (1 - 1 / z), ay * (1 - 1 / z), z

    return transform


def zoom_warp(img: np.ndarray, x0: float, y0: float, z: float) -> np.ndarray:
    """``img (H, W, C)``'s window at ``(x0, y0)`` magnified ``z`` times, at the same size
    (bilinear)."""
    import cv2

    m = np.array([[z, 0.0, -x0 * z], [0.0, z, -y0 * z]])
    return cv2.warpAffine(img, m, (img.shape[1], img.shape[0]), flags=cv2.INTER_LINEAR)


def _crop_copy(seq: MotSequence, name: str, root: Path, offset, less_w: int, less_h: int):
    """``seq``'s frames cropped to windows ``less_w`` / ``less_h`` pixels narrower / shorter
    at ``offset(i) = (dx, dy)`` (see :func:`_copy`'s ``box_shift``)."""
    w, h = seq.width - less_w, seq.height - less_h

    def crop(img, i):
        dx, dy = offset(i)
        return np.ascontiguousarray(img[dy : dy + h, dx : dx + w])

    return _copy(seq, name, root, crop, box_shift=(offset, w, h))


def _copy(
    seq: MotSequence,
    name: str,
    root: Path,
    fn,
    box_scale: float = 1.0,
    every: int = 1,
    box_shift: tuple | None = None,
) -> MotSequence:
    """``seq``'s frames through ``fn(frame (H, W, C) uint8 RGB, index)``, written once as the
    MOTChallenge folder ``root / name`` (PNG frames; ground truth and public detections with
    their boxes times ``box_scale``); with ``every`` > 1 only frames 0, every, 2 every, ...
    (renumbered, the frame rate divided); with ``box_shift = (offset(i), width, height)`` the
    boxes of frame i moved by ``-offset(i) = -(dx, dy)`` pixels and those less than half
    inside ``width`` x ``height`` (along either axis) dropped (a crop)."""
    import cv2

    out = root / name
    if not (out / "seqinfo.ini").is_file():
        (out / "img1").mkdir(parents=True, exist_ok=True)
        (out / "gt").mkdir(exist_ok=True)
        n = 0
        with seq.open() as src:
            for i, frame in src.items():
                if frame is None or i >= seq.n_frames:
                    raise SystemExit(f"{seq.name}: frame {i + 1} unreadable")
                if i % every:
                    continue
                img = fn(frame.permute(1, 2, 0).numpy(), i)
                n += 1
                cv2.imwrite(str(out / "img1" / f"{n:06d}.png"), img[..., ::-1])
        h, w = img.shape[:2]
        write_mot(
            out / "gt" / "gt.txt", _copied_rows(seq.gt, box_scale, every, box_shift), kind="gt"
        )
        if seq.det_path is not None:
            (out / "det").mkdir(exist_ok=True)
            write_mot(
                out / "det" / "det.txt",
                _copied_rows(seq.detections(), box_scale, every, box_shift),
                kind="det",
            )
        rate = (seq.frame_rate or 25) / every
        (out / "seqinfo.ini").write_text(
            f"[Sequence]\nname={name}\nimDir=img1\nframeRate={max(1, round(rate))}\n"
            f"seqLength={n}\nimWidth={w}\nimHeight={h}\nimExt=.png\n"
        )
    return load_mot_sequence(out)


def _copied_rows(rows: MotRows, s: float, every: int, shift: tuple | None = None) -> MotRows:
    """``rows`` with boxes times ``s`` on the frames kept by ``every`` (renumbered); with
    ``shift = (offset(i), width, height)`` moved by minus the frame's offset ``(dx, dy)``
    (then times ``z`` where the offset is ``(dx, dy, z)``: a magnified window), those less
    than half inside the ``width`` x ``height`` frame (along either axis) dropped."""
    keep = rows.frames % every == 0
    boxes = rows.boxes * s
    if shift is not None:
        offset, width, height = shift
        boxes = boxes.copy()
        d = np.array([offset(int(f)) for f in rows.frames], dtype=np.float64)
        d = d.reshape(len(rows.frames), -1)
        boxes[:, :2] -= d[:, :2]
        if d.shape[1] == 3:
            boxes *= d[:, 2:3]
        for axis, size in ((0, width), (1, height)):
            lo, ext = boxes[:, axis], boxes[:, axis + 2]
            inside = np.clip(lo + ext, 0, size) - np.clip(lo, 0, size)
            keep &= inside >= 0.5 * ext
    return MotRows(rows.frames[keep] // every, rows.ids[keep], boxes[keep], rows.conf[keep])


SCAN_KEYS = (
    "model",
    "scan_box_regression",
    "scan_min_scale",
    "scan_max_scale",
    "scan_scale_step",
    "scan_stride",
    "scan_nms",
    "min_frame_height",
    "scan_vote",
    "scan_pad",
    "scan_cascade",
    "detection_threshold",
)


def own_detections(seq: MotSequence, cache: Path, params: dict | None = None) -> MotRows:
    """The bundled model's scan of every frame at the tracker's scan settings (the defaults,
    or those of ``params``), cached as a MOT det file (object boxes, calibrated
    probabilities)."""
    scan_params = {k: v for k, v in (params or {}).items() if k in SCAN_KEYS}
    cfg = MultiTrackerConfig(**scan_params)
    # every scan setting, and the digest of the model's content (its tensors and description,
    # not its signature): a retrained or edited model of the same name never reads the scans
    # of the one before
    digest = read_model_metadata(resolve_model(cfg.model))["sha256"][:12]
    # a model file by its name alone (its digest tells files of one name apart): a path's
    # folders would make folders in the cache
    named = {
        k: Path(str(getattr(cfg, k))).stem if k == "model" else getattr(cfg, k) for k in SCAN_KEYS
    }
    key = "_".join([seq.name, *(str(named[k]) for k in SCAN_KEYS), digest])
    path = cache / f"own_{key}.txt"
    if path.is_file():
        return read_mot(path, 1.0, seq.n_frames, kind="det")
    mt = MultiTargetTracker(**scan_params)
    f_, b_, p_ = [], [], []
    t0 = time.perf_counter()
    with seq.open() as src:
        for i, frame in src.items():
            if frame is None or i >= seq.n_frames:
                continue
            boxes, p = mt.detect(frame)
            f_.append(np.full(len(p), i))
            b_.append(boxes.numpy())
            p_.append(p.numpy())
    rows = MotRows.from_arrays(
        np.concatenate(f_), np.full(sum(len(p) for p in p_), -1), np.concatenate(b_),
        np.concatenate(p_),
    )  # fmt: skip
    cache.mkdir(parents=True, exist_ok=True)
    write_mot(path, rows, kind="det")
    print(f"scanned {seq.name} in {time.perf_counter() - t0:.0f} s -> {path}", file=sys.stderr)
    return read_mot(path, 1.0, seq.n_frames, kind="det")  # the same rounding as a cache hit


def run_one(
    seq: MotSequence,
    dets: MotRows | None,
    params: dict,
    seed: int,
    own: bool,
    scan_workers: int = 0,
) -> dict:
    """One tracked run, scored. ``dets`` None: the tracker scans every frame itself, as
    ``torchtrack track`` does (``scan_workers`` processes scanning ahead: the same tracks)."""
    mt = MultiTargetTracker(generator=torch.Generator().manual_seed(seed), **params)
    with seq.open() as src:  # cached scans go in as the tracker's own scans
        rows = track_sequence(
            mt, src, dets, max_frames=seq.n_frames, as_scans=own and dets is not None,
            scan_workers=scan_workers if dets is None else 0,
        )  # fmt: skip
    m = score_mot(seq.gt, rows, seq.n_frames, name=seq.name)
    return {"hota": 100 * m.hota, "mota": 100 * m.mota, "idf1": 100 * m.idf1}


def parse_grid(spec: str) -> tuple[str, list]:
    key, _, values = spec.partition("=")
    if key not in {f.name for f in dataclasses.fields(MultiTrackerConfig)} or not values:
        raise SystemExit(f"--grid must be KEY=v1,v2,... with a MultiTrackerConfig key: {spec!r}")
    # the CLI's reading of `key=value` (true / false / null / numbers), checked like a config
    out = [parse_tracker_spec(f"multi:{key}={v}")[1][key] for v in values.split(",")]
    try:
        out = [getattr(apply_overrides(MultiTrackerConfig(), {key: v}), key) for v in out]
    except ConfigError as exc:
        raise SystemExit(f"--grid {spec!r}: {exc}") from None
    return key, out


def parse_fixed(spec: str, grid_key: str) -> dict:
    """``--set key=v,key2=v2`` -> the overrides, checked like a config."""
    if not spec:
        return {}
    out = parse_tracker_spec(f"multi:{spec}")[1]
    if grid_key in out:
        raise SystemExit(f"--set names the grid's key {grid_key!r}")
    try:
        apply_overrides(MultiTrackerConfig(), out)
    except ConfigError as exc:
        raise SystemExit(f"--set {spec!r}: {exc}") from None
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", required=True, help="KEY=v1,v2,... (one MultiTrackerConfig key)")
    ap.add_argument(
        "--set",
        default="",
        metavar="KEY=V,...",
        help="other keys held at these values for every candidate (not the defaults)",
    )
    ap.add_argument("--seeds", default="0,1,2,3")
    ap.add_argument(
        "--settings",
        default=",".join(f"{k}:{s}" for k in KINDS for s in SEQUENCES if (k, s) != ("public", SEQUENCES[0])),
        help="KIND:SEQUENCE,... with KIND own, public (TUD only) or gt",
    )  # fmt: skip
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--cache", type=Path, default=REPO / "runs" / "loso_multi")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--live",
        type=int,
        metavar="WORKERS",
        help="own detections scanned live by every run, as `torchtrack track` scans (the "
        "ground plane shapes each scan), with this many scan-ahead processes, instead of the "
        "cached scans: slower, and what the command gives",
    )
    ap.add_argument(
        "--rescale",
        type=float,
        metavar="S",
        help="score on copies of the sequences resized by S (ground truth and detections too)",
    )
    ap.add_argument(
        "--every",
        type=int,
        metavar="K",
        help="score on copies of the sequences keeping every K-th frame (a K times lower rate)",
    )
    ap.add_argument(
        "--pan",
        type=float,
        metavar="V",
        help="score on copies of the sequences seen by a camera panning V px a frame (a "
        "cropped window sliding right and back)",
    )
    ap.add_argument(
        "--shake",
        type=int,
        metavar="A",
        help="score on copies of the sequences seen by a shaking camera (a cropped window at a "
        "random offset of up to 2 A px on both axes each frame)",
    )
    ap.add_argument(
        "--zoom",
        type=float,
        metavar="R",
        help="score on copies of the sequences seen by a camera moving towards the scene and "
        "back (magnified 1 + R a frame about the horizon up to 1.5x, then back)",
    )
    ap.add_argument(
        "--degrade",
        metavar="contrast=C,noise=S[,gray=1]",
        help="score on copies of the sequences with lowered contrast and added sensor noise "
        "(gray=1: made grey first)",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    key, values = parse_grid(args.grid)
    fixed = parse_fixed(args.set, key)
    seeds = [int(s) for s in args.seeds.split(",")]
    settings = [tuple(s.split(":", 1)) for s in args.settings.split(",")]
    for kind, name in settings:
        if kind not in KINDS or name not in SEQUENCES or (kind, name) == ("public", SEQUENCES[0]):
            raise SystemExit(f"unknown setting {kind}:{name}")
    seqs = {name: load(args.data, name) for name in {n for _, n in settings}}
    if args.every is not None and args.every != 1:  # subsampled() refuses K < 1
        seqs = {n: subsampled(s, args.every, args.cache) for n, s in seqs.items()}
    if args.rescale is not None and args.rescale != 1:  # rescaled() refuses S <= 0
        seqs = {n: rescaled(s, args.rescale, args.cache) for n, s in seqs.items()}
    if args.pan is not None:
        seqs = {n: panned(s, args.pan, args.cache) for n, s in seqs.items()}
    if args.shake is not None:
        seqs = {n: shaken(s, args.shake, args.cache) for n, s in seqs.items()}
    if args.zoom is not None:
        seqs = {n: zoomed(s, args.zoom, args.cache) for n, s in seqs.items()}
    if args.degrade:
        seqs = {n: degraded(s, args.degrade, args.cache) for n, s in seqs.items()}
    res: dict[tuple, list[dict]] = {}
    t0 = time.perf_counter()
    for kind, name in settings:
        seq = seqs[name]
        base = None
        if kind == "own" and args.live is None:
            base = own_detections(seq, args.cache, fixed)
        elif kind == "public":
            d = seq.detections()
            base = dataclasses.replace(
                d, conf=score_probabilities(torch.from_numpy(d.conf)).numpy()
            )
        for v in values:
            if kind == "own" and key in SCAN_KEYS and args.live is None:
                base = own_detections(seq, args.cache, {**fixed, key: v})  # the scan changes
            for seed in seeds:
                dets = gt_as_detections(seq.gt, seed) if kind == "gt" else base
                r = run_one(
                    seq, dets, {**fixed, key: v}, seed, own=kind == "own",
                    scan_workers=args.live or 0,
                )  # fmt: skip
                res.setdefault((kind, name, v), []).append(r)
                print(f"{kind}:{name} {key}={v} seed {seed}: HOTA {r['hota']:.1f} "
                      f"MOTA {r['mota']:.1f} IDF1 {r['idf1']:.1f}", file=sys.stderr, flush=True)  # fmt: skip

    def hota(kind, name, v):
        return statistics.mean(r["hota"] for r in res[(kind, name, v)])

    default = getattr(MultiTrackerConfig(), key)
    head = " | ".join(f"{k}: {n}" for k, n in settings)
    lines = [
        f"HOTA mean ± sd over seeds {args.seeds} (MOTA / IDF1 means); default {key} = {default}"
        + (f"; held: {args.set}" if args.set else ""),
        "",
        f"| {key} | {head} |",
        "|---" * (len(settings) + 1) + "|",
    ]
    for v in values:
        cells = []
        for kind, name in settings:
            rs = res[(kind, name, v)]
            h = [r["hota"] for r in rs]
            sd = statistics.stdev(h) if len(h) > 1 else 0.0
            cells.append(
                f"{statistics.mean(h):.1f} ± {sd:.1f} ({statistics.mean(r['mota'] for r in rs):.1f}"
                f" / {statistics.mean(r['idf1'] for r in rs):.1f})"
            )
        mark = " (default)" if v == default else ""
        lines.append(f"| {v}{mark} | " + " | ".join(cells) + " |")
    own = [n for k, n in settings if k == "own"]
    if len(own) == 2:
        held = []
        for tune, test in (own, own[::-1]):
            best = max(values, key=lambda v: hota("own", tune, v))
            held.append(
                f"chosen on {tune}: {key} = {best}, {test} scores {hota('own', test, best):.1f}"
            )
        lines += ["", "Leave one sequence out (own detections): " + "; ".join(held) + "."]  # fmt: skip
    lines.append(f"\n{time.perf_counter() - t0:.0f} s; command: python tools/loso_multi.py "
                 + " ".join(argv if argv is not None else sys.argv[1:]))  # fmt: skip
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
