import pytest
import torch

from torchtrack.errors import BoxError, ConfigError, ShapeError
from torchtrack.filter.motion import BachooMotion, ChateauAR, KleinAR, default_chateau_A

BOXES = torch.tensor([[10.0, 20.0, 30.0, 60.0], [100.0, 50.0, 8.0, 16.0]], dtype=torch.float64)


@pytest.mark.parametrize("model", [KleinAR(), ChateauAR(window=(15.0, 30.0)), BachooMotion()])
def test_box_round_trip_and_init_shapes(model):
    s = model.from_boxes(BOXES)
    torch.testing.assert_close(model.to_boxes(s), BOXES)
    g = torch.Generator().manual_seed(0)
    p = model.init(BOXES, 64, g)
    assert p.shape == (2, 64, model.dim) and p.dtype == torch.float64
    q = model.predict(p, g)
    assert q.shape == p.shape and torch.isfinite(q).all()
    q32 = model.predict(p.float(), g)
    assert q32.dtype == torch.float32
    with pytest.raises(ShapeError, match=r"states must be \(B, N, "):
        model.predict(p[..., :3], g)
    with pytest.raises(ShapeError, match=r"boxes must be \(B, 4\)"):
        model.from_boxes(BOXES[0])


def test_klein_eq1_moments():
    m = KleinAR()  # paper defaults 6.4 / 0.64
    g = torch.Generator().manual_seed(1)
    n = 200_000
    s = m.from_boxes(BOXES[:1]).unsqueeze(1).repeat(1, n, 1)
    s[..., 4] = 3.0  # vx
    q = m.predict(s, g)
    dv = q[..., 4] - 3.0
    assert abs(dv.std().item() - 6.4) < 0.05 and abs(dv.mean().item()) < 0.05
    # x_t = x_{t-1} + v_t exactly (eq. 1), w random walk with sigma 0.64
    torch.testing.assert_close(q[..., 0], s[..., 0] + q[..., 4])
    assert abs((q[..., 2] - 30.0).std().item() - 0.64) < 0.01
    # init: velocities ~ N(0, 6.4^2), positions on the box (Klein sec. II-B)
    p = m.init(BOXES[:1], n, g)
    assert abs(p[..., 5].std().item() - 6.4) < 0.05 and (p[..., 0] == 25.0).all()


def test_chateau_predict_matches_eq4_moments():
    a = torch.eye(6, dtype=torch.float64) * 0.5
    b = torch.zeros(6, 2, dtype=torch.float64)
    b[0, 0], b[4, 1], b[1, 0] = 1.0, 1.0, 1.0
    sigma = torch.tensor([[4.0, 0.1], [0.1, 0.01]], dtype=torch.float64)
    m = ChateauAR(a, b, sigma)
    x = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0, 6.0], dtype=torch.float64)
    n = 200_000
    q = m.predict(x.expand(1, n, 6).clone(), torch.Generator().manual_seed(2))[0]
    torch.testing.assert_close(q.mean(0), a @ x, atol=0.02, rtol=0)
    cov = torch.cov(q.T)
    torch.testing.assert_close(cov, b @ sigma @ b.T, atol=0.05, rtol=0.03)


def test_chateau_config_errors():
    with pytest.raises(ConfigError, match="A must be 6 x 6"):
        ChateauAR(A=torch.eye(5))
    with pytest.raises(ConfigError, match="Sigma must be 3 x 3 to match B"):
        ChateauAR(Sigma=torch.eye(2))
    with pytest.raises(ConfigError, match="positive semi-definite"):
        ChateauAR(Sigma=-torch.eye(3))
    with pytest.raises(ConfigError, match="unknown parameter keys"):
        ChateauAR.from_params({"A": [], "B": [], "Sigma": [], "sigma": 1})
    with pytest.raises(ConfigError, match=r"window must be \(w, h\) > 0"):
        ChateauAR(window=(0.0, 1.0))
    # window=5 was TypeError "object of type 'int' has no len()"; ragged from_params lists
    # were torch's ValueError naming no parameter
    for bad in (5, "ab", (1.0, "2"), (True, 1.0), (1.0, 2.0, 3.0)):
        with pytest.raises(ConfigError, match=r"window must be \(w, h\) > 0 and finite, two num"):
            ChateauAR(window=bad)
    good = {"A": default_chateau_A().tolist(), "B": [[1.0]] * 6, "Sigma": [[1.0]]}
    with pytest.raises(ConfigError, match=r"window must be .* got 5"):
        ChateauAR.from_params({**good, "window": 5})
    for key, bad in (
        ("A", [[1.0] * 6] * 5 + [[1.0]]),
        ("B", [[1.0], "x"] * 3),
        ("Sigma", [1, [2]]),
    ):
        with pytest.raises(ConfigError, match=rf"ChateauAR: {key} must be a matrix of numbers"):
            ChateauAR.from_params({**good, key: bad})
    with pytest.raises(ConfigError, match="ChateauAR: A must hold real numbers"):
        ChateauAR(A=torch.ones(6, 6, dtype=torch.bool))
    assert ChateauAR.from_params({**good, "window": [15, 30]}).window == (15.0, 30.0)


def test_bachoo_noise_adapts_and_inflates_on_occlusion():
    m = BachooMotion(min_sigma=1.0, gain=1.0, occluded_sigma=20.0, history=25)
    h = m.new_history(BOXES)
    torch.testing.assert_close(m.noise_std(h), torch.ones(2, 2, dtype=torch.float64))
    for _ in range(30):  # more than the 25-frame history
        h = m.update_history(h, torch.tensor([[5.0, -0.2], [0.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(
        m.noise_std(h), torch.tensor([[5.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    )
    h2 = m.update_history(
        h, torch.zeros(2, 2, dtype=torch.float64), occluded=torch.tensor([False, True])
    )
    sd = m.noise_std(h2)
    assert sd[1].tolist() == [20.0, 20.0] and sd[0, 0] == pytest.approx(24 * 5 / 25)
    # eq. (1): position noise std follows the adapted sigma; eq. (3) v = x_t - x_{t-1}
    n = 100_000
    s = m.from_boxes(BOXES).unsqueeze(1).repeat(1, n, 1)
    s[..., 4] = 2.0
    q = m.predict(s, torch.Generator().manual_seed(3), history=h2)
    dx = q[..., 0] - s[..., 0] - 2.0
    assert dx[0].std().item() == pytest.approx(sd[0, 0].item(), rel=0.02)
    assert dx[1].std().item() == pytest.approx(20.0, rel=0.02)
    torch.testing.assert_close(q[..., 4:6], q[..., 0:2] - s[..., 0:2])
    assert (q[..., 6].std(1) - 0.02).abs().max() < 0.001  # eq. (4) rotation
    assert ((q[..., 2] / 30.0)[0].std() - 0.01).abs() < 0.001  # eq. (2) relative scale
    with pytest.raises(ShapeError, match="history is for B=2 targets"):
        m.predict(s[:1], None, history=h2)
    # a wrong-length occluded was taken and failed in predict as torch's broadcast error, a
    # list velocity was AttributeError
    with pytest.raises(
        ShapeError, match=r"occluded must be None or a tensor \(B,\) = \(2,\), got \(3,\)"
    ):
        m.update_history(h, torch.zeros(2, 2), occluded=torch.tensor([True, False, True]))
    with pytest.raises(ShapeError, match=r"occluded must be None or a tensor .* got list"):
        m.update_history(h, torch.zeros(2, 2), occluded=[True, False])
    with pytest.raises(
        ShapeError, match=r"velocity must be a tensor \(B, 2\) = \(2, 2\), got list"
    ):
        m.update_history(h, [[0.0, 0.0], [1.0, 1.0]])
    with pytest.raises(ShapeError, match=r"velocity must be a tensor .* got \(2,\)"):
        m.update_history(h, torch.zeros(2))
    with pytest.raises(ConfigError, match=r"history must be an integer in \[1, 100000\]"):
        BachooMotion(history=0)
    with pytest.raises(ConfigError, match="min_sigma must be a finite number >= 0"):
        BachooMotion(min_sigma=-1)


@pytest.mark.parametrize("model", [KleinAR(), ChateauAR(window=(15.0, 30.0)), BachooMotion()])
def test_confine_keeps_particles_from_running_away(model):
    """A lost target's particles stop at the frame border: centre clamped, velocity along the
    clamped axis zeroed, size at most twice the frame; particles inside are unchanged."""
    frame = (240, 320)
    g = torch.Generator().manual_seed(0)
    s = model.init(torch.tensor([[150.0, 100.0, 30.0, 60.0]], dtype=torch.float64), 50, g)
    torch.testing.assert_close(model.confine(s, frame), s)
    # push every particle far right and down with a large velocity, and grow them
    far = s.clone()
    far[..., 0] += 10_000
    far[..., 1] -= 5_000
    if isinstance(model, ChateauAR):
        far[..., 2:4] = far[..., 0:2] - 50  # c_{t-1}: moving at 50 px / frame
        far[..., 4:6] = 1e4
    else:
        far[..., 4:6] = 50.0
        far[..., 2:4] = 1e6
    c = model.confine(far, frame)
    assert torch.equal(c[..., 0], torch.full_like(c[..., 0], 320.0))
    assert torch.equal(c[..., 1], torch.zeros_like(c[..., 1]))
    boxes = model.to_boxes(c)
    assert bool((boxes[..., 2] <= 640 + 1e-6).all()) and bool((boxes[..., 3] <= 480 + 1e-6).all())
    if isinstance(model, ChateauAR):
        assert torch.equal(c[..., 2:4], c[..., 0:2])  # no velocity left
    else:
        assert bool((c[..., 4:6] == 0).all())
    for _ in range(50):  # predicting on stays near the frame
        c = model.confine(model.predict(c, g), frame)
    assert bool((c[..., 0] <= 320).all()) and bool((c[..., 1] >= 0).all())
    nan = s.clone()
    nan[0, 0, 0] = float("nan")
    assert torch.isfinite(model.confine(nan, frame)[..., :2]).all()


def test_klein_relative_noise_follows_the_size_and_keeps_the_shape():
    # relative: velocity noise sigma * sqrt(w h) (floored at min_sigma pixels); sizes change by
    # exp(common +- aspect), so the log aspect ratio moves less than the log scale
    m = KleinAR(0.1, 0.02, relative=True, aspect=0.25, min_sigma=1.5)
    g = torch.Generator().manual_seed(3)
    n = 200_000
    s = m.from_boxes(BOXES).unsqueeze(1).repeat(1, n, 1)
    q = m.predict(s, g)
    dv = q[..., 4]
    assert abs(dv[0].std().item() - 0.1 * (30 * 60) ** 0.5) < 0.05
    assert abs(dv[1].std().item() - 1.5) < 0.02  # 0.1 * sqrt(8 * 16) = 1.13 < min_sigma
    ls = 0.5 * (q[..., 2].log() + q[..., 3].log()) - 0.5 * (s[..., 2].log() + s[..., 3].log())
    la = 0.5 * (q[..., 2].log() - q[..., 3].log()) - 0.5 * (s[..., 2].log() - s[..., 3].log())
    assert abs(ls.std().item() - 0.02) < 0.001 and abs(la.std().item() - 0.005) < 0.0003
    # noise_scale multiplies the velocity noise per row
    q2 = m.predict(s, g, noise_scale=torch.tensor([2.0, 1.0], dtype=torch.float64))
    assert abs(q2[0, :, 4].std().item() - 2 * 0.1 * (30 * 60) ** 0.5) < 0.1
    # damping shrinks the velocity before the noise
    d = KleinAR(0.0, 0.0, relative=True, damping=0.5)
    s[..., 4] = 4.0
    torch.testing.assert_close(d.predict(s, g)[..., 4], torch.full_like(s[..., 4], 2.0))
    with pytest.raises(ConfigError, match="damping must be in"):
        KleinAR(damping=1.5)


def test_klein_paper_mode_is_eq1_unchanged():
    # the paper mode draws the same numbers as before the relative mode existed
    m = KleinAR()
    s = m.init(BOXES, 16, torch.Generator().manual_seed(4))
    g = torch.Generator().manual_seed(5)
    e = torch.randn((2, 16, 4), generator=g, dtype=torch.float64)
    e *= torch.tensor([6.4, 6.4, 0.64, 0.64], dtype=torch.float64)
    ref = s.clone()
    ref[..., 4:6] += e[..., 0:2]
    ref[..., 0:2] += ref[..., 4:6]
    ref[..., 2:4] = (ref[..., 2:4] + e[..., 2:4]).clamp_min(1.0)
    torch.testing.assert_close(m.predict(s, torch.Generator().manual_seed(5)), ref)


@pytest.mark.parametrize("model", [KleinAR(), ChateauAR(window=(15.0, 30.0)), BachooMotion()])
@pytest.mark.parametrize("size", [(True, 320), (240, -1), (float("nan"), 320), (240,)])
def test_confine_refuses_a_frame_size_that_is_not_two_sizes(model, size):
    """confine took (True, 320) as a 1 x 320 frame, a negative or NaN size as given (centres
    clamped into a mirrored or NaN frame), silently; it checks frame_size like clip_boxes."""
    s = model.init(torch.tensor([[150.0, 100.0, 30.0, 60.0]], dtype=torch.float64), 5)
    with pytest.raises(ShapeError, match=r"frame_size must be \(H, W\)"):
        model.confine(s, size)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: KleinAR(sigma_xy=float("inf")), r"sigma_xy must be a finite number >= 0, got inf"),
        (lambda: KleinAR(sigma_wh=True), r"sigma_wh must be a finite number >= 0, got True"),
        (lambda: KleinAR(min_size="1"), r"min_size must be a finite number >= 0, got '1'"),
        (lambda: KleinAR(damping=True), r"damping must be in \[0, 1\], got True"),
        (lambda: KleinAR(relative="no"), r"relative must be True or False, got 'no'"),
        (lambda: BachooMotion(gain=float("inf")), r"gain must be a finite number >= 0"),
        (lambda: BachooMotion(history=2.5), r"history must be an integer in \[1, 100000\]"),
        (lambda: BachooMotion(history=True), r"history must be an integer in \[1, 100000\]"),
        (lambda: BachooMotion(history=10**12), r"history must be an integer in \[1, 100000\]"),
        (lambda: ChateauAR(window=(float("inf"), 30.0)), r"window must be \(w, h\) > 0 and finite"),
        (lambda: ChateauAR(min_scale=float("inf")), r"min_scale must be a finite number >= 0"),
        (
            lambda: ChateauAR(A=torch.full((6, 6), float("nan"))),
            r"ChateauAR: A must be finite",
        ),
        (
            lambda: ChateauAR(B=torch.full((6, 3), float("inf"))),
            r"ChateauAR: B must be finite",
        ),
    ],
)
def test_motion_settings_that_are_not_finite_numbers_are_refused(make, match):
    """KleinAR(sigma_xy=inf) and the like were taken (every particle then inf, reset to the
    frame centre by confine), True as 1, '1' as 1.0; BachooMotion(history=2.5) ran with 2 and
    history=10^12 asked for 16 TB at new_history; ChateauAR took an infinite window and NaN
    matrices (NaN particles)."""
    with pytest.raises(ConfigError, match=match):
        make()


@pytest.mark.parametrize("model", [KleinAR(), ChateauAR(window=(15.0, 30.0)), BachooMotion()])
def test_motion_init_refuses_bad_counts_and_boxes(model):
    """init(boxes, -1) was torch's RuntimeError, n=True one particle and n=2.5 a TypeError deep
    in torch; a NaN or infinite box, or one of size <= 0, gave NaN or negative-size particles,
    silently."""
    box = torch.tensor([[150.0, 100.0, 30.0, 60.0]], dtype=torch.float64)
    assert model.init(box, 3).shape[:2] == (1, 3)
    for n in (0, -1, True, 2.5):
        with pytest.raises(ConfigError, match=r"n must be an integer >= 1 \(particles per box\)"):
            model.init(box, n)
    for bad, what in (
        ([[150.0, float("nan"), 30.0, 60.0]], r"boxes\[1\] is not finite"),
        ([[150.0, 100.0, float("inf"), 60.0]], r"boxes\[1\] is not finite"),
        ([[150.0, 100.0, -30.0, 60.0]], r"boxes\[1\] = .* has a size below 1.0 pixel"),
        ([[150.0, 100.0, 30.0, 0.0]], r"boxes\[1\] = .* has a size below 1.0 pixel"),
    ):
        boxes = torch.tensor([[1.0, 2.0, 3.0, 4.0], *bad], dtype=torch.float64)
        with pytest.raises(BoxError, match=what):
            model.init(boxes, 3)
        with pytest.raises(BoxError, match=r"boxes\[1\]"):
            model.from_boxes(boxes)


@pytest.mark.parametrize("model", [KleinAR(), ChateauAR()])
@pytest.mark.parametrize("bad", [2.0, torch.ones(3), torch.ones(2, 1), torch.ones(6)])
def test_a_noise_scale_of_the_wrong_shape_is_a_shape_error(model, bad):
    # a float was AttributeError ('float' object has no attribute 'to'), a wrong length
    # torch's broadcast RuntimeError
    s = model.init(torch.tensor([[10.0, 10.0, 20.0, 20.0], [30.0, 30.0, 10.0, 10.0]]), 5)
    with pytest.raises(ShapeError, match=r"noise_scale must be None or a tensor \(B,\) = \(2,\)"):
        model.predict(s, noise_scale=bad)
    assert model.predict(s, noise_scale=torch.ones(2)).shape == s.shape


@pytest.mark.parametrize("model", [KleinAR(), ChateauAR(window=(15.0, 30.0)), BachooMotion()])
def test_integer_states_are_a_shape_error(model):
    """Integer states reached torch's NotImplementedError "'normal_kernel_cpu' not implemented
    for 'Long'"."""
    s = model.init(BOXES, 4, torch.Generator().manual_seed(0))
    with pytest.raises(ShapeError, match=r"states must be floating point, got torch\.int64"):
        model.predict(s.long(), torch.Generator().manual_seed(0))
