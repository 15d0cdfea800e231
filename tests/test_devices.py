"""Every part of the pipeline on every device: the tensors it makes follow its input's device.

Each test runs on the CPU and, where an NVIDIA GPU is present, on CUDA (skipped with a reason
elsewhere: no GPU on CI). A CUDA run is compared with the same call on the CPU: features and
detector scores must agree to float tolerance, the detector's scan must find the same people,
and the trackers (whose random streams differ between devices) must follow the same person.
Frames are the bundled demo clip (PETS 2009 S2.L1), so no data folder is needed.
"""

from __future__ import annotations

import itertools

import pytest
import torch

from torchtrack.boxes import box_iou_matrix
from torchtrack.data import demo_clip_path
from torchtrack.io.video import open_source

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available (no GPU)")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]
SINGLE = ["adaptive-haar", "cotrain", "histogram", "template", "detector", "fused"]


@pytest.fixture(scope="module")
def frames() -> list[torch.Tensor]:
    """The first 12 frames of the demo clip, ``(3, 360, 480)`` uint8 RGB on the CPU."""
    src = open_source(demo_clip_path())
    try:
        return [f for _, f in itertools.islice(src.items(), 12)]
    finally:
        src.close()


@pytest.fixture(scope="module")
def pedestrian():
    from torchtrack.track.detector_pf import resolve_detector

    return resolve_detector("pedestrian")


@pytest.fixture(scope="module")
def person(frames, pedestrian) -> torch.Tensor:
    """``(4,)`` the object box of the most confident person on the first frame (CPU scan)."""
    boxes, p = pedestrian.scan(frames[0], min_scale=0.4)
    assert len(p), "the demo's first frame has people"
    return boxes[int(p.argmax())].double()


def _gen(device: str, seed: int = 0) -> torch.Generator:
    return torch.Generator(device=device).manual_seed(seed)


@pytest.mark.parametrize("device", DEVICES)
def test_integral_channels_follow_the_device(frames, device):
    from torchtrack.features.channels import channel_integrals, compute_channels
    from torchtrack.features.integral import integral_image, rgb_to_gray

    f = frames[0][None]
    ref_ii = integral_image(rgb_to_gray(f.float()))
    got_ii = integral_image(rgb_to_gray(f.to(device).float()))
    assert got_ii.device.type == device
    torch.testing.assert_close(got_ii.cpu(), ref_ii, rtol=1e-5, atol=1e-2)
    ref = channel_integrals(f)
    got = channel_integrals(f.to(device))
    # channels in float32 (GPU and CPU round transcendental functions differently in the last
    # bits), summed in float64: the tables agree to float32 rounding of the pixels summed
    for k in range(ref.max_level() + 1):
        a, b = ref.level(k), got.level(k)
        assert b.device.type == device
        torch.testing.assert_close(b.cpu(), a, rtol=0, atol=1e-5 * float(a.abs().amax()))
    ch_ref = compute_channels(f.float())
    ch = compute_channels(f.to(device).float())
    torch.testing.assert_close(ch.cpu(), ch_ref, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("device", DEVICES)
def test_detector_scan_on_device_finds_the_same_people(frames, pedestrian, device):
    ref_boxes, ref_p = pedestrian.scan(frames[0], min_scale=0.4)
    boxes, p = pedestrian.scan(frames[0].to(device), min_scale=0.4)
    assert boxes.device.type == device and p.device.type == device
    assert len(p) == len(ref_p)
    iou = box_iou_matrix(ref_boxes.double(), boxes.double().cpu())
    assert bool((iou.max(1).values > 0.99).all())
    torch.testing.assert_close(p.cpu().sort().values, ref_p.sort().values, rtol=0, atol=1e-4)
    # the batched scan (B, C, H, W) too
    out = pedestrian.scan(torch.stack(frames[:2]).to(device), min_scale=0.4)
    assert len(out) == 2 and out[1][0].device.type == device


@pytest.mark.parametrize("device", DEVICES)
def test_detector_scores_on_device(frames, pedestrian, person, device):
    win = pedestrian.object_to_window(person[None])[None].float()  # (1, 1, 4)
    shifted = win + torch.tensor([[[-4.0, 3.0, 0.0, 0.0]], [[6.0, -2.0, 4.0, 8.0]]]).transpose(0, 1)
    ref = pedestrian.score(frames[0][None], shifted)
    got = pedestrian.score(frames[0][None].to(device), shifted.to(device))
    assert got.device.type == device
    # boosted trees: a feature within float32 rounding of a split flips one leaf, which moves a
    # probability by that leaf's share (about 0.01 seen on an H100), never more than a few
    torch.testing.assert_close(got.cpu(), ref, rtol=0, atol=0.05)


@pytest.mark.parametrize("device", DEVICES)
def test_platt_calibration_on_device(device):
    from torchtrack.learn.calibration import PlattCalibrator

    g = torch.Generator().manual_seed(0)
    y = (torch.rand(500, generator=g) < 0.4).double()
    s = 2.0 * y - 1.0 + torch.randn(500, generator=g, dtype=torch.float64)
    ref = PlattCalibrator().fit(s, y)
    got = PlattCalibrator().fit(s.to(device), y.to(device))
    p = got.predict_proba(s.to(device))
    assert p.device.type == device
    torch.testing.assert_close(p.cpu(), ref.predict_proba(s), rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", SINGLE)
def test_single_target_tracker_on_device(frames, person, name, device):
    """Each tracker follows the demo's most confident person over 11 frames on ``device`` as on
    the CPU: its state stays on the frame's device and its box stays on that person."""
    from torchtrack.track.base import create_tracker, tracker_info

    def run(dev: str) -> torch.Tensor:
        kw = {"generator": _gen(dev)} if tracker_info(name).accepts_generator else {}
        tr = create_tracker(name, **kw)
        st = tr.init(frames[0].to(dev), person.to(dev))
        for f in frames[1:]:
            st = tr.update(f.to(dev))
        assert bool(torch.isfinite(st.box).all())
        return st.box[0].double().cpu()

    ref, got = run("cpu"), run(device)
    iou = box_iou_matrix(ref[None], got[None])[0, 0]
    assert iou > 0.5, f"{name} on {device}: box {got.tolist()} vs CPU {ref.tolist()}"


@pytest.mark.parametrize("device", DEVICES)
def test_multi_target_tracker_on_device(frames, device):
    """The multi-target tracker with frames on ``device`` (its scan and particle likelihood run
    there; its targets stay on the CPU) reports the people the CPU run reports."""
    from torchtrack.track.multi import MultiTargetTracker

    def run(dev: str):
        mt = MultiTargetTracker("pedestrian", generator=_gen("cpu"))
        for f in frames:
            out = mt.update(f.to(dev))
        assert mt.states.device.type == "cpu" and out.boxes.device.type == "cpu"
        return out

    ref, got = run("cpu"), run(device)
    assert len(ref) > 0 and len(got) == len(ref)
    iou = box_iou_matrix(ref.boxes.double(), got.boxes.double().cpu())
    assert bool((iou.max(1).values > 0.5).all())


@pytest.mark.parametrize("device", DEVICES)
def test_eval_runner_on_device(frames, person, device, tmp_path):
    """``run_sequence(..., device=...)``: frames go to the device, results come back on the CPU."""
    import cv2

    from torchtrack.eval.runner import run_sequence
    from torchtrack.io.sequences import load_sequence

    seq_dir = tmp_path / "demo"
    (seq_dir / "img").mkdir(parents=True)
    for i, f in enumerate(frames):
        cv2.imwrite(
            str(seq_dir / "img" / f"{i + 1:04d}.jpg"), f.permute(1, 2, 0).numpy()[..., ::-1]
        )
    x, y, w, h = person.tolist()
    (seq_dir / "groundtruth_rect.txt").write_text(
        "\n".join(f"{x + 1:.2f},{y + 1:.2f},{w:.2f},{h:.2f}" for _ in frames) + "\n"
    )
    seq = load_sequence(seq_dir)[0]
    res = run_sequence("detector", seq, device=device)
    assert res.error is None, res.traceback
    assert res.boxes.device.type == "cpu" and bool(torch.isfinite(res.boxes).all())
    assert res.n_updates == len(frames) - 1


@pytest.mark.parametrize("device", DEVICES)
def test_cli_track_on_device(person, device, tmp_path, capsys):
    """``torchtrack track --device``: one target with --box, and every target, write their
    files from a run on ``device``."""
    from torchtrack.cli import main

    box = ",".join(f"{v:.1f}" for v in person.tolist())
    one, every = tmp_path / "one.csv", tmp_path / "every.mot.txt"
    common = ["track", "demo", "--max-frames", "8", "--device", device, "--no-progress"]
    assert main([*common, "--box", box, "--tracker", "detector", "--out", str(one)]) == 0
    assert main([*common, "--mot", str(every), "--scan-workers", "0"]) == 0
    assert len(one.read_text().splitlines()) == 9  # header + 8 frames
    assert every.read_text().strip(), capsys.readouterr().out


@pytest.mark.parametrize("device", DEVICES)
def test_track_sequence_moves_frames_to_the_device(device):
    """``track_sequence(..., device=...)`` (``torchtrack eval --mot --trackers multi``)."""
    from torchtrack.track.multi import MultiTargetTracker, track_sequence

    src = open_source(demo_clip_path())
    try:
        mt = MultiTargetTracker("pedestrian", generator=_gen("cpu"))
        rows = track_sequence(mt, src, max_frames=6, device=device)
    finally:
        src.close()
    assert mt.frame_index == 5 and len(rows) > 0


@pytest.mark.parametrize("device", DEVICES)
def test_scans_run_on_the_device_a_batch_of_frames_at_a_time(device, monkeypatch):
    """``track_sequence(device=...)`` without scan workers (``torchtrack track --device cuda``):
    the scans run on the frames' device, a GPU's 8 frames at a time (one batched call each),
    the CPU's one at a time; the people found are the CPU run's."""
    from torchtrack.track.multi import MultiTargetTracker, track_sequence

    seen = []
    batch = MultiTargetTracker.detect_batch

    def spy(self, frames, lines):
        seen.append((frames.device.type, frames.shape[0]))
        return batch(self, frames, lines)

    def run(dev):
        mt = MultiTargetTracker("pedestrian", generator=_gen("cpu"))
        with open_source(demo_clip_path()) as src:
            return track_sequence(mt, src, max_frames=17, device=dev, scan_workers=0)

    ref = run("cpu")
    monkeypatch.setattr(MultiTargetTracker, "detect_batch", spy)
    got = run(device)
    assert seen == (
        [("cuda", 8), ("cuda", 8), ("cuda", 1)] if device == "cuda" else [("cpu", 1)] * 17
    )
    last = int(ref.frames.max())
    a, b = ref.boxes[ref.frames == last], got.boxes[got.frames == last]
    assert len(a) > 0 and len(b) == len(a)
    iou = box_iou_matrix(torch.as_tensor(a).double(), torch.as_tensor(b).double())
    assert bool((iou.max(1).values > 0.5).all())
