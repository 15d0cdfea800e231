"""The co-training tracker: registry, config, synthetic tracking, bad input, real data."""

import pytest
import torch

from torchtrack.boxes import box_iou
from torchtrack.errors import ConfigError
from torchtrack.track.base import create_tracker, tracker_names
from torchtrack.track.cotrain import CoTrainConfig, CoTrainTracker, load_cotrain_config

SMALL = {"n_selectors": 6, "max_samples": 400, "particles": 100}


def frame(cx: float, cy: float, seed: int, gray: bool = False) -> torch.Tensor:
    """A 20x20 red checkered target over noise; (C, 90, 120) uint8 (parts may leave the frame)."""
    g = torch.Generator().manual_seed(seed)
    f = torch.zeros(3, 90, 120)
    f[0] = 40 + 10 * torch.rand(90, 120, generator=g)
    f[1] = 90 + 30 * torch.rand(90, 120, generator=g)
    f[2] = 140 + 30 * torch.rand(90, 120, generator=g)
    yy, xx = torch.meshgrid(torch.arange(90), torch.arange(120), indexing="ij")
    inside = ((xx - cx).abs() < 10) & ((yy - cy).abs() < 10)
    checker = (((yy // 2) + (xx // 2)) % 2).float()
    f[0] = torch.where(inside, 200 + 40 * checker, f[0])
    f[1] = torch.where(inside, 30 + 20 * checker, f[1])
    f[2] = torch.where(inside, torch.full_like(f[2], 30.0), f[2])
    f = f.round().to(torch.uint8)
    if gray:
        f = (0.299 * f[0] + 0.587 * f[1] + 0.114 * f[2]).round().to(torch.uint8)[None]
    return f


def run(tracker, path, gray=False):
    states = [tracker.init(frame(*path[0], 0, gray), [path[0][0] - 10, path[0][1] - 10, 20, 20])]
    for i, (cx, cy) in enumerate(path[1:], 1):
        states.append(tracker.update(frame(cx, cy, i, gray)))
    return states


@pytest.mark.parametrize("resampler", ["seir", "sir"])
def test_follows_a_moving_target(resampler):
    t = create_tracker(
        "cotrain", generator=torch.Generator().manual_seed(0), resampler=resampler, **SMALL
    )
    path = [(30 + 3 * i, 40 + 1.5 * i) for i in range(12)]
    states = run(t, path)
    for st, (cx, cy) in zip(states[-4:], path[-4:], strict=True):
        gt = torch.tensor([cx - 10, cy - 10, 20, 20], dtype=torch.float64)
        assert float(box_iou(st.box[0], gt)) > 0.5
        assert bool(st.visible[0])
    assert len(t.history) == 11 and all(h["ess"] > 0 for h in t.history)
    assert states[-1].particles.shape == (1, 100, 2)


def test_gray_video_uses_the_documented_fallback():
    t = CoTrainTracker(generator=torch.Generator().manual_seed(0), **SMALL)
    path = [(40 + 2 * i, 45) for i in range(6)]
    states = run(t, path, gray=True)
    assert [c.n_features_in_ for c in t.trainer.classifiers] == [1, 2]
    gt = torch.tensor([path[-1][0] - 10, 35, 20, 20], dtype=torch.float64)
    assert float(box_iou(states[-1].box[0], gt)) > 0.3


def test_target_leaving_the_frame_and_missing_blob():
    t = CoTrainTracker(generator=torch.Generator().manual_seed(0), **SMALL)
    path = [(100 + 6 * i, 45) for i in range(10)]  # walks out through the right edge
    states = run(t, path)
    assert not bool(states[-1].visible[0])  # gone: no blob
    # While nothing is found the model is frozen.
    hists = [c.hist_.clone() for c in t.trainer.classifiers]
    st = t.update(frame(-50, -50, 99))  # a frame without the target
    assert not bool(st.visible[0]) and st.confidence[0] == 0
    assert not t.history[-1]["accepted"]
    for h, c in zip(hists, t.trainer.classifiers, strict=True):
        torch.testing.assert_close(c.hist_, h)
    assert torch.isfinite(st.box).all()


def test_registry_config_and_errors(tmp_path):
    assert "cotrain" in tracker_names()
    assert load_cotrain_config("configs/trackers/cotrain.toml") == CoTrainConfig()
    cfg = tmp_path / "c.toml"
    cfg.write_text("[cotrain]\nparticles = 50\nresampler = 'sir'\n")
    t = CoTrainTracker(config=str(cfg), max_iter=2)
    assert (t.config.particles, t.config.resampler, t.config.max_iter) == (50, "sir", 2)
    cfg.write_text("particles = 50\nresampler = 'sir'\n")  # the top level, without a table
    assert CoTrainTracker(config=str(cfg)).config.particles == 50
    # a key above the table was dropped without a word (the default 300 particles taken)
    cfg.write_text("particles = 50\n[cotrain]\nresampler = 'sir'\n")
    with pytest.raises(ConfigError, match=r"key\(s\) 'particles' outside the \[cotrain\] table"):
        CoTrainTracker(config=str(cfg))
    cfg.write_text("cotrain = 5\n")  # a TypeError ('int' object is not a mapping)
    with pytest.raises(ConfigError, match=r"'cotrain' must be the \[cotrain\] table .* got 5"):
        CoTrainTracker(config=str(cfg))
    cfg.write_text("partcles = 50\n")
    with pytest.raises(ConfigError, match="partcles"):
        CoTrainTracker(config=str(cfg))
    with pytest.raises(ConfigError, match="unknown cotrain parameter"):
        create_tracker("cotrain", sharpnes=2.0)
    with pytest.raises(ConfigError, match="unknown resampler"):
        create_tracker("cotrain", resampler="pf")
    with pytest.raises(ConfigError, match="particles must be"):
        CoTrainTracker(particles=0)
    with pytest.raises(ConfigError, match="must be int"):
        CoTrainTracker(particles=1.5)
    # a bool is no number: motion_std = true ran as 1.0 (the other fields refused it)
    with pytest.raises(ConfigError, match="motion_std must be float, got True"):
        CoTrainTracker(motion_std=True)
    with pytest.raises(ConfigError, match="unknown positives"):
        CoTrainTracker(positives="box")
    with pytest.raises(ConfigError, match="cannot read"):
        CoTrainTracker(config=str(tmp_path / "missing.toml"))


@pytest.mark.slow
def test_real_pedestrian_sequence(data_dir):
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(data_dir / "tracking" / "bobot_pedestrian")[0].head(8)
    t = CoTrainTracker(generator=torch.Generator().manual_seed(0))
    ious = []
    for i, fr in enumerate(seq.open()):
        if i == 0:
            t.init(fr, seq.boxes[0])
            continue
        ious.append(float(box_iou(t.update(fr).box[0], seq.boxes[i].double())))
    assert sum(ious) / len(ious) > 0.5


@pytest.mark.slow
def test_replayed_positives_stop_the_classifier_collapse(data_dir):
    """Couple, first 12 frames: the frame-2 blob is too weak for new positives; trained on the
    border negatives alone, the classifiers call every pixel background from frame 4 on and the
    track is lost for good. Replaying positives of the labelled set keeps the target."""
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(data_dir / "tracking" / "otb" / "Couple")[0].head(12)
    frames = list(seq.open())
    seen = {}
    for replay in (0, 500):
        t = CoTrainTracker(generator=torch.Generator().manual_seed(0), replay=replay)
        t.init(frames[0], seq.boxes[0])
        seen[replay] = [bool(t.update(f).visible[0]) for f in frames[1:]]
    assert not any(seen[0][4:])
    assert all(seen[500])


def test_velocity_widening_and_scale_options():
    # a fast target (7 px / frame, beyond the random walk's reach for a 20 px target) with the
    # running velocity and the lost-target widening; the scale search keeps a 20 px box sane
    t = create_tracker(
        "cotrain",
        generator=torch.Generator().manual_seed(0),
        velocity=0.5,
        lost_growth=0.2,
        scale_step=0.05,
        **SMALL,
    )
    path = [(20 + 7 * i, 45) for i in range(12)]
    states = run(t, path)
    gt = torch.tensor([path[-1][0] - 10, 35, 20, 20], dtype=torch.float64)
    assert float(box_iou(states[-1].box[0], gt)) > 0.4
    assert t.velocity[0] > 3 and 10 < t.size[0] < 40
    for bad, match in (
        ({"velocity": 1.5}, "velocity must be in"),
        ({"lost_growth": 1.0}, "lost_growth must be in"),
        ({"max_search_scale": 1.0}, "max_search_scale"),
        ({"scale_ring": 1.0}, "scale_ring must be"),
    ):
        with pytest.raises(ConfigError, match=match):
            CoTrainTracker(**bad)
