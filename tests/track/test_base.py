"""The tracker interface: validation, call order, TrackState, registry and specs."""

from __future__ import annotations

import pytest
import torch

import torchtrack.track.base as base
from torchtrack.boxes import box_iou
from torchtrack.errors import BoxError, ConfigError, ShapeError, TrackerError
from torchtrack.track.base import (
    Tracker,
    TrackState,
    available_trackers,
    create_tracker,
    parse_tracker_spec,
    register_tracker,
    tracker_names,
)
from torchtrack.track.opencv import has_contrib


class Shift(Tracker):
    """Moves the box by (dx, 0) each frame: obviously right behaviour to check the plumbing."""

    name = "test-shift"
    max_targets = None

    def __init__(self, dx: float = 1.0) -> None:
        super().__init__()
        self.dx = dx

    def _init(self, frame, boxes):
        self.boxes = boxes.clone()
        return TrackState(
            box=self.boxes.clone(),
            confidence=torch.ones(len(boxes), dtype=torch.float64),
            visible=torch.ones(len(boxes), dtype=torch.bool),
        )

    def _update(self, frame):
        self.boxes[:, 0] += self.dx
        return TrackState(
            box=self.boxes.clone(),
            confidence=torch.ones(len(self.boxes), dtype=torch.float64),
            visible=torch.ones(len(self.boxes), dtype=torch.bool),
        )


@pytest.fixture
def registered():
    register_tracker("test-shift", Shift, description="test")
    yield
    base._REGISTRY.pop("test-shift", None)


FRAME = torch.zeros(3, 20, 30, dtype=torch.uint8)


def test_init_update_batched_and_single():
    t = Shift(dx=2)
    s0 = t.init(FRAME, [1, 2, 5, 6])
    assert s0.box.shape == (1, 4) and s0.box.dtype == torch.float64
    s1 = t.update(FRAME)
    assert s1.box[0].tolist() == [3, 2, 5, 6]
    t2 = Shift()
    s = t2.init(FRAME, torch.tensor([[1.0, 2, 5, 6], [10, 2, 5, 6]]))
    assert s.box.shape == (2, 4)
    assert t2.update(FRAME).box[:, 0].tolist() == [2, 11]


def test_call_order_and_frame_checks():
    t = Shift()
    with pytest.raises(TrackerError, match=r"update\(\) called before init\(\)"):
        t.update(FRAME)
    with pytest.raises(ShapeError, match=r"\(C, H, W\) uint8"):
        t.init(FRAME.float(), [1, 1, 4, 4])
    with pytest.raises(ShapeError, match=r"\(C, H, W\) uint8"):
        t.init(FRAME[None], [1, 1, 4, 4])
    with pytest.raises(ShapeError, match=r"must be a torch\.Tensor"):
        t.init(FRAME.numpy(), [1, 1, 4, 4])
    t.init(FRAME[:1], [1, 1, 4, 4])  # gray frames are accepted
    with pytest.raises(ShapeError, match="frame size changed"):
        t.update(torch.zeros(3, 21, 30, dtype=torch.uint8))
    # but not a gray frame after RGB ones (or back): it was tracked, compared with RGB models
    t.init(FRAME, [1, 1, 4, 4])
    with pytest.raises(ShapeError, match="frame channels changed from 3 to 1 during tracking"):
        t.update(FRAME[:1])


def test_bad_init_boxes():
    t = Shift()
    with pytest.raises(BoxError, match="size below"):
        t.init(FRAME, [1, 1, 0, 4])
    # the documented minimum: a box of 1-2 pixels is refused, 3 pixels is tracked
    with pytest.raises(BoxError, match=r"size below 3.0 pixel\(s\), the smallest init box"):
        t.init(FRAME, [1, 1, 2, 5])
    t.init(FRAME, [1, 1, 3, 3])
    with pytest.raises(BoxError, match="outside the 30x20 frame"):
        t.init(FRAME, [40, 1, 4, 4])
    with pytest.raises(BoxError, match="not finite"):
        t.init(FRAME, [float("nan"), 1, 4, 4])
    with pytest.raises(ShapeError, match=r"\(4,\) or \(B, 4\)"):
        t.init(FRAME, [1, 1, 4])
    # not numbers at all: torch's own TypeError / ValueError ("new(): invalid data type 'str'")
    for box in ("1,1,4,4", [1, 1, "4", 4], [[1, 1, 4, 4], [1, 1]], [1, None, 4, 4]):
        with pytest.raises(ShapeError, match=r"init box must be \(4,\) or \(B, 4\) numbers"):
            t.init(FRAME, box)
    with pytest.raises(TrackerError, match="needs an initial box"):
        t.init(FRAME, None)


def test_init_box_of_bools_or_complex_and_meta_frames_are_refused():
    """A complex box lost its imaginary part with only torch's UserWarning and was tracked; a
    bool box was read as 0 / 1 pixels (refused as 'a size below 3'); a frame on the meta device
    failed inside the tracker with torch's 'item() cannot be called on meta tensors'."""
    t = Shift()
    with pytest.raises(ShapeError, match=r"real numbers x, y, w, h, got torch.complex64"):
        t.init(FRAME, torch.tensor([1.0, 1, 4, 4], dtype=torch.complex64))
    with pytest.raises(ShapeError, match=r"real numbers x, y, w, h, got torch.bool"):
        t.init(FRAME, torch.ones(4, dtype=torch.bool))
    with pytest.raises(ShapeError, match="on the 'meta' device"):
        t.init(FRAME.to("meta"), [1, 1, 4, 4])
    t.init(FRAME, [1, 1, 4, 4])
    with pytest.raises(ShapeError, match="on the 'meta' device"):
        t.update(FRAME.to("meta"))


def test_max_targets():
    class One(Shift):
        name = "one"
        max_targets = 1

    with pytest.raises(TrackerError, match="at most 1 target"):
        One().init(FRAME, [[1, 1, 4, 4], [2, 2, 4, 4]])


def test_trackstate_shapes():
    s = TrackState.single([1, 2, 3, 4], confidence=0.5, visible=False)
    assert (
        s.box.shape == (1, 4) and s.confidence.tolist() == [0.5] and s.visible.tolist() == [False]
    )
    with pytest.raises(ShapeError, match=r"\(B, 4\)"):
        TrackState(torch.zeros(4), torch.zeros(1), torch.zeros(1, dtype=torch.bool))
    with pytest.raises(ShapeError, match=r"must be \(2,\)"):
        TrackState(torch.zeros(2, 4), torch.zeros(1), torch.zeros(2, dtype=torch.bool))


def test_registry(registered):
    assert "test-shift" in tracker_names() and "mil" in tracker_names()
    assert "mil" in available_trackers() and "camshift" in available_trackers()
    t = create_tracker("test-shift", dx=3.0)
    assert isinstance(t, Shift) and t.dx == 3.0
    with pytest.raises(
        ConfigError, match=r"unknown tracker 'nope'; known trackers: .*camshift.*mil"
    ):
        create_tracker("nope")
    with pytest.raises(ConfigError, match=r"has no parameter\(s\) speed; valid: dx"):
        create_tracker("test-shift", speed=2)
    register_tracker("test-shift", Shift)  # same factory again: fine
    with pytest.raises(ConfigError, match="already registered"):
        register_tracker("test-shift", lambda: Shift())


@pytest.mark.skipif(has_contrib(), reason="opencv-contrib is installed: csrt is available")
def test_contrib_tracker_without_contrib_says_what_to_install():
    assert "csrt" in tracker_names() and "csrt" not in available_trackers()
    with pytest.raises(ConfigError, match="needs opencv-contrib-python-headless"):
        create_tracker("csrt")


def test_parse_tracker_spec():
    assert parse_tracker_spec("mil") == ("mil", {})
    assert parse_tracker_spec("adaptive-haar:adapt=none,particles=500,lam=20.5,fast=true") == (
        "adaptive-haar",
        {"adapt": "none", "particles": 500, "lam": 20.5, "fast": True},
    )
    with pytest.raises(ConfigError, match="is not key=value"):
        parse_tracker_spec("mil:fast")
    with pytest.raises(ConfigError, match="has no name"):
        parse_tracker_spec(":a=1")
    with pytest.raises(ConfigError, match="nothing after ':'"):
        parse_tracker_spec("histogram: ")  # was the tracker "histogram" labelled "histogram:"


def test_tracker_spec_numbers_are_ascii_without_underscores():
    """int() reads 1_0 as 10 and Arabic-Indic digits as a number: the spec
    histogram:n_particles=1_0 ran 10 particles, silently. Such text stays a string, which the
    typed settings refuse by name; plain numbers, exponents and words parse as before."""
    _, p = parse_tracker_spec("histogram:n_particles=1_0,lam=2_5.0,a=\u0665\u0660,b=1e3,c=my_model")
    assert p == {
        "n_particles": "1_0",
        "lam": "2_5.0",
        "a": "\u0665\u0660",
        "b": 1000.0,
        "c": "my_model",
    }
    with pytest.raises(ConfigError, match=r"'n_particles' must be an integer, got '1_0'"):
        create_tracker("histogram", **parse_tracker_spec("histogram:n_particles=1_0")[1])


def test_a_broken_tracker_module_only_warns(monkeypatch):
    monkeypatch.setattr(base, "_loaded", False)
    monkeypatch.setattr(
        base, "BUILTIN_TRACKER_MODULES", [*base.BUILTIN_TRACKER_MODULES, "torchtrack.no_such_mod"]
    )
    with pytest.warns(RuntimeWarning, match=r"tracker module torchtrack\.no_such_mod could not"):
        names = tracker_names()
    assert "mil" in names and "camshift" in names


# ------------------------------------------------- the one visibility rule (issue 12)
def test_a_box_mostly_outside_the_frame_is_never_visible():
    """Whatever a tracker believes, a box with less than half of its area inside the frame
    (or a non-finite box) is reported not visible."""
    t = Shift(dx=5)  # 20 x 30 frame, the box moves right 5 px a frame and always says visible
    st = t.init(FRAME, torch.tensor([[10.0, 5.0, 10.0, 10.0], [0.0, 0.0, 4.0, 4.0]]))
    assert st.visible.tolist() == [True, True]
    seen = []
    for _ in range(6):
        st = t.update(FRAME)
        seen.append(st.visible.tolist())
    # box 0 at x = 15, 20, 25 (half inside), 30 (outside), 35, 40; box 1 at x = 5 ... 30
    assert [v[0] for v in seen] == [True, True, True, False, False, False]
    assert [v[1] for v in seen] == [True, True, True, True, True, False]
    t.boxes[0, 2] = float("nan")
    assert t.update(FRAME).visible.tolist() == [False, False]


def test_init_box_mostly_outside_is_not_visible():
    t = Shift()
    st = t.init(FRAME, torch.tensor([27.0, 5.0, 10.0, 10.0]))  # 3 of 10 columns inside
    assert st.visible.tolist() == [False]


def _leaving_clip(data_dir, n=30, width=120):
    """BoBoT frames 900.. seen through a 120-px window panning right at 4 px a frame, so the
    walker (x ~ 140-190) leaves the view on the left after ~25 frames: real frames, a target
    that really leaves. Returns the frames and the walker's box on the first one."""
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(data_dir / "tracking" / "bobot_pedestrian")[0]
    src = seq.open("rgb")
    frames = []
    for i, fr in src.items():
        if i >= 900 + n:
            break
        if i >= 900:
            o = 80 + 4 * (i - 900)
            frames.append(fr[:, :, o : o + width].contiguous())
    src.close()
    box = seq.boxes[900].clone()
    box[0] -= 80
    return frames, box


LEAVING_TRACKERS = [
    ("detector", {"n_particles": 200}),
    ("adaptive-haar", {"adapt": "global", "n_particles": 500}),
    ("adaptive-haar", {"adapt": "none", "n_particles": 500}),
    ("adaptive-haar", {"adapt": "per-particle", "n_particles": 200}),
    ("histogram", {"n_particles": 500}),
    ("template", {}),
    ("cotrain", {}),
    ("fused", {}),
    ("mil", {}),
    ("camshift", {}),
]


@pytest.mark.parametrize("name, params", LEAVING_TRACKERS, ids=lambda v: str(v))
def test_a_target_that_leaves_is_never_visible_outside_the_frame(
    data_dir, one_thread, name, params
):
    """Every tracker on a walker who leaves the view: no row reports visible with the box
    mostly outside the frame, and the box stays near the frame (it does not run away)."""
    from torchtrack.boxes import inside_fraction

    frames, box = _leaving_clip(data_dir)
    if base.tracker_info(name).accepts_generator:
        params = {**params, "generator": torch.Generator().manual_seed(0)}
    t = create_tracker(name, **params)
    h, w = frames[0].shape[-2:]
    st = t.init(frames[0], box)
    for f in frames[1:]:
        st = t.update(f)
        frac = inside_fraction(st.box.double(), (h, w))
        assert not bool((st.visible & ~(frac >= 0.5)).any()), (name, st.box.tolist())
        cx = st.box[:, 0] + st.box[:, 2] / 2
        assert bool(((cx >= -w) & (cx <= 2 * w)).all()), (name, st.box.tolist())


@pytest.mark.slow
def test_issue_12_bobot_case_lost_target_is_not_visible_outside(data_dir, one_thread):
    """The issue's case: adaptive-haar, adapt=global, seed 0, the whole BoBoT sequence from
    --box 107.93,46.553,55.69,156.017. Before: from frame 990 the box left the 320x240 frame
    and ran away (x = 678 at the last frame) with visible=1. Now no visible row lies mostly
    outside the frame and the box stays on it."""
    from torchtrack.boxes import inside_fraction
    from torchtrack.io.video import open_source

    t = create_tracker("adaptive-haar", adapt="global", generator=torch.Generator().manual_seed(0))
    src = open_source(data_dir / "tracking" / "bobot_pedestrian" / "frames")
    rows = []
    for i, f in src.items():
        st = t.init(f, torch.tensor([107.93, 46.553, 55.69, 156.017])) if i == 0 else t.update(f)
        rows.append((st.box[0].clone(), bool(st.visible[0])))
    assert len(rows) == 1017
    boxes = torch.stack([b for b, _ in rows]).double()
    visible = torch.tensor([v for _, v in rows])
    frac = inside_fraction(boxes, (240, 320))
    assert not bool((visible & (frac < 0.5)).any())
    cx, cy = boxes[:, 0] + boxes[:, 2] / 2, boxes[:, 1] + boxes[:, 3] / 2
    assert bool(((cx >= 0) & (cx <= 320) & (cy >= 0) & (cy <= 240)).all())


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("adaptive-haar", {"n_particles": 100}),
        ("cotrain", {"n_selectors": 6, "max_samples": 400, "particles": 100}),
        ("histogram", {"n_particles": 100}),
        ("template", {}),
    ],
)
def test_colour_trackers_follow_a_gray_sequence(name, params):
    # the documented behaviour on C = 1 frames (docs/tracking.md, "Gray frames"): every tracker
    # runs on the single channel and follows a target that differs from the background in
    # brightness
    g = torch.Generator().manual_seed(0)
    bg = torch.randint(0, 120, (1, 60, 80), dtype=torch.uint8, generator=g)
    frames = []
    for t in range(5):
        f = bg.clone()
        f[0, 20:40, 20 + 2 * t : 36 + 2 * t] = 240
        frames.append(f)
    tr = create_tracker(name, generator=torch.Generator().manual_seed(1), **params)
    tr.init(frames[0], [20, 20, 16, 20])
    for f in frames[1:]:
        st = tr.update(f)
    gt = torch.tensor([28.0, 20.0, 16.0, 20.0], dtype=torch.float64)
    assert float(box_iou(st.box[0].to(torch.float64), gt)) > 0.5


_HUGE = 10**9


@pytest.mark.parametrize(
    "name, overrides, match",
    [
        # particles: 10^9 asked for 48 GB at init() (a RuntimeError traceback from the CLI);
        # 10^6 for up to 7.5 GB in one frame
        ("histogram", {"n_particles": _HUGE}, r"n_particles must be in \[1, 100000\]"),
        ("adaptive-haar", {"n_particles": _HUGE}, r"n_particles must be in \[1, 100000\]"),
        ("detector", {"n_particles": _HUGE}, r"n_particles must be in \[1, 100000\]"),
        ("template", {"n_particles": _HUGE}, r"n_particles must be in \[1, 100000\]"),
        ("fused", {"n_particles": _HUGE}, r"n_particles must be in \[1, 100000\]"),
        ("cotrain", {"particles": _HUGE}, r"particles must be in \[1, 100000\]"),
        (
            "detector",
            {"n_particles": 1000, "n_targets": 1000},
            r"n_particles x n_targets = 1000 x 1000 is more than 100000 particles",
        ),
        # sizes of per-frame samples, histograms, pools and buffers
        ("histogram", {"n_h": _HUGE}, r"n_h must be in \[1, 256\]"),
        ("histogram", {"n_s": 257}, r"n_s must be in \[1, 256\]"),
        ("histogram", {"n_v": _HUGE}, r"n_v must be in \[1, 256\]"),
        ("histogram", {"grid": _HUGE}, r"n_particles x grid\^2 = 2000 x 1000000000\^2 is more"),
        ("adaptive-haar", {"n_weak": _HUGE}, r"n_weak must be in \[1, 1024\]"),
        (
            "adaptive-haar",
            {"n_weak": 1024, "n_particles": 100000},
            r"n_particles x n_weak = 100000 x 1024 is more than 16777216",
        ),
        ("adaptive-haar", {"pos_max": _HUGE}, r"pos_max must be in \[1, 10000\]"),
        ("adaptive-haar", {"neg_max": _HUGE}, r"neg_max must be in \[1, 10000\]"),
        ("adaptive-haar", {"neg_candidates": _HUGE}, r"neg_candidates must be in \[1, 100000\]"),
        ("template", {"template_size": _HUGE}, r"n_particles x template_size\^2 = 400 x"),
        ("template", {"history": _HUGE}, r"history must be in \[1, 100000\]"),
        ("template", {"lk_iterations": _HUGE}, r"lk_iterations must be in \[0, 1000\]"),
        ("cotrain", {"n_selectors": _HUGE}, r"n_selectors must be in \[1, 100\]"),
        ("cotrain", {"n_candidates": _HUGE}, r"n_candidates must be in \[1, 100\]"),
        ("cotrain", {"opening_size": _HUGE}, r"opening_size must be in \[1, 255\]"),
        ("cotrain", {"init_passes": _HUGE}, r"init_passes must be in \[1, 100\]"),  # hung
        ("cotrain", {"max_iter": _HUGE}, r"max_iter must be in \[0, 1000\]"),
        ("fused", {"n_selectors": _HUGE}, r"n_selectors must be in \[1, 100\]"),
        ("fused", {"n_candidates": _HUGE}, r"n_candidates must be in \[1, 100\]"),
    ],
)
def test_sizes_that_exhaust_memory_are_refused_when_the_tracker_is_made(name, overrides, match):
    """Counts that size a tracker's tensors were bounded only by 2^31 - 1: 10^9 particles,
    histogram bins, weak classifiers, training examples, template pixels or boosting
    selectors asked for gigabytes to exabytes at init() or on the first frame (the CLI
    printed torch's allocation error as a traceback), and 10^9 co-training passes or
    Lucas-Kanade steps ran for ever. They are refused when the tracker is made, naming the
    setting and its bound; the bounds are far above the papers' values (the particle bound
    50 times the largest, 2000) and were run on the corpus clip within 3.5 GB."""
    with pytest.raises(ConfigError, match=match):
        create_tracker(name, **overrides)


@pytest.mark.parametrize(
    "name, overrides",
    [
        ("histogram", {"n_particles": 100000, "n_h": 256, "n_s": 256, "n_v": 256}),
        ("histogram", {"n_particles": 2000, "grid": 128}),
        ("adaptive-haar", {"n_weak": 512, "n_particles": 32768, "pos_max": 10000}),
        ("detector", {"n_particles": 100000}),
        ("template", {"n_particles": 400, "template_size": 289, "history": 100000}),
        ("cotrain", {"particles": 100000, "n_selectors": 100, "n_candidates": 100}),
        ("fused", {"n_particles": 100000, "n_selectors": 100, "n_candidates": 100}),
    ],
)
def test_sizes_at_their_bounds_are_accepted(name, overrides):
    create_tracker(name, **overrides)


@pytest.mark.parametrize(
    "name", ["histogram", "adaptive-haar", "template", "cotrain", "detector", "fused", "multi"]
)
def test_a_generator_that_is_not_a_torch_generator_is_refused_when_the_tracker_is_made(name):
    """generator=5 was 'int' object is not iterable (or has no attribute 'device') on the first
    frame, a string a 'sequence of 4' generators, and a list of generators worked in some
    trackers and not in others (adaptive-haar drew its negatives' x and y from the list's two
    first generators): every tracker takes one torch.Generator or None, as documented."""
    from torchtrack.track.multi import MultiTargetTracker

    make = (
        (lambda **k: MultiTargetTracker("pedestrian", **k))
        if name == "multi"
        else (lambda **k: create_tracker(name, **k))
    )
    for bad, what in ((5, "int"), ("seed", "str"), ([torch.Generator()], "list")):
        with pytest.raises(
            ConfigError, match=rf"generator must be a torch.Generator or None, got {what}"
        ):
            make(generator=bad)
    make(generator=torch.Generator().manual_seed(0))
    make(generator=None)


@pytest.mark.parametrize("bad", [True, 2.5, "3", None])
def test_a_config_instance_is_type_checked_like_its_toml(bad):
    """config=HistogramTrackerConfig(n_particles=True) ran one particle and 2.5 went on, where
    the same value in a TOML file or a keyword is refused; '3' and None were TypeErrors in
    validate()."""
    from torchtrack.track.config import HistogramTrackerConfig

    with pytest.raises(ConfigError, match=r"histogram tracker: 'n_particles' must be an integer"):
        create_tracker("histogram", config=HistogramTrackerConfig(n_particles=bad))
    t = create_tracker("histogram", config=HistogramTrackerConfig(n_particles=50))
    assert t.config == HistogramTrackerConfig(n_particles=50)


def test_a_float_setting_given_an_integer_beyond_the_float_range_is_a_config_error():
    """sigma_xy=10**400 (a keyword, a TOML integer or a config object's field) was float()'s
    OverflowError traceback."""
    from torchtrack.track.config import HistogramTrackerConfig

    for kw in ({"sigma_xy": 10**400}, {"config": HistogramTrackerConfig(sigma_xy=10**400)}):
        with pytest.raises(ConfigError, match=r"sigma_xy must be a finite number within .*401 dig"):
            create_tracker("histogram", **kw)
