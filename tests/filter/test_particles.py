import math

import pytest
import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
from torchtrack.filter.particles import (
    ParticleSet,
    best_particle,
    dominant_mode_mean,
    ess,
    normalize_log_weights,
    uniform_log_weights,
    weighted_cov,
    weighted_mean,
)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normalize_and_ess_match_plain_formulas(dtype):
    g = torch.Generator().manual_seed(0)
    # offset beyond exp's float32 range (88): plain exp / sum would overflow
    lw = torch.randn(5, 50, generator=g, dtype=dtype) * 3 + 100
    out, rec = normalize_log_weights(lw)
    assert out.dtype == dtype and not rec.any()
    w = torch.softmax(lw.double(), 1)
    tol = 1e-4 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(out.exp().double(), w, atol=tol, rtol=tol)
    # Jin et al. eq. (11)-(12)
    torch.testing.assert_close(ess(lw).double(), 1 / (w**2).sum(1), rtol=tol, atol=0)


def test_ess_extremes():
    lw = torch.tensor([[0.0, 0.0, 0.0, 0.0], [0.0, -math.inf, -math.inf, -math.inf]])
    torch.testing.assert_close(ess(lw), torch.tensor([4.0, 1.0]))


def test_all_zero_weights_recover_uniform_and_flag():
    lw = torch.tensor([[-math.inf] * 4, [0.0, 1.0, -math.inf, 2.0]], dtype=torch.float64)
    out, rec = normalize_log_weights(lw)
    assert rec.tolist() == [True, False]
    torch.testing.assert_close(out[0], torch.full((4,), -math.log(4), dtype=torch.float64))
    assert torch.isfinite(out[1, [0, 1, 3]]).all() and out[1, 2] == -math.inf
    assert not torch.isnan(out).any()


def test_nan_log_weights_raise_naming_step():
    lw = torch.tensor([[0.0, float("nan")]])
    with pytest.raises(FilterError, match="my_step: log-weights contain NaN"):
        normalize_log_weights(lw, step="my_step")
    with pytest.raises(FilterError, match=r"\+inf"):
        normalize_log_weights(torch.tensor([[0.0, math.inf]]))


def test_log_weights_without_particles_or_of_bools_are_shape_errors():
    """resample() and normalize_log_weights() of (B, 0) log-weights restarted the rows at
    -log(0), Python's ValueError 'math domain error'; bool log-weights reached torch's
    subtraction (RuntimeError); a list an AttributeError."""
    from torchtrack.filter.resample import resample

    for fn in (normalize_log_weights, resample, ess):
        with pytest.raises(ShapeError, match=r"log_weights must be \(B, N\) numbers with N >= 1"):
            fn(torch.zeros(2, 0))
        with pytest.raises(ShapeError, match=r"numbers with N >= 1, got \(2, 3\) torch.bool"):
            fn(torch.zeros(2, 3, dtype=torch.bool))
    with pytest.raises(ShapeError, match=r"log_weights must be \(B, N\), got list"):
        normalize_log_weights([[0.0, 0.0]])
    assert resample(torch.zeros(0, 3))[0].shape == (0, 3)  # no rows: nothing to do


def test_estimates_against_loops():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(3, 20, 4, generator=g, dtype=torch.float64)
    lw = torch.randn(3, 20, generator=g, dtype=torch.float64)
    w = torch.softmax(lw, 1)
    for b in range(3):
        ref = sum(w[b, i] * x[b, i] for i in range(20))
        torch.testing.assert_close(weighted_mean(x, lw)[b], ref)
        c = sum(w[b, i] * torch.outer(x[b, i] - ref, x[b, i] - ref) for i in range(20))
        torch.testing.assert_close(weighted_cov(x, lw)[b], c)
        torch.testing.assert_close(best_particle(x, lw)[b], x[b, int(lw[b].argmax())])


def test_dominant_mode_beats_mean_on_bimodal_posterior():
    g = torch.Generator().manual_seed(2)
    n = 2000
    a = torch.randn(2, n // 2, 2, generator=g, dtype=torch.float64) + torch.tensor([0.0, 0.0])
    b = torch.randn(2, n // 2, 2, generator=g, dtype=torch.float64) + torch.tensor([20.0, 0.0])
    x = torch.cat([a, b], 1)
    lw = torch.cat(
        [torch.full((2, n // 2), math.log(0.7)), torch.full((2, n // 2), math.log(0.3))], 1
    )
    lw = lw.double()
    mean = weighted_mean(x, lw)
    mode = dominant_mode_mean(x, lw)
    assert (mean[:, 0] - 6.0).abs().max() < 0.5  # the mean lies between the modes
    assert (mode - torch.tensor([0.0, 0.0], dtype=torch.float64)).norm(dim=1).max() < 0.3
    # explicit bandwidth path
    mode2 = dominant_mode_mean(x, lw, bandwidth=torch.tensor([1.0, 1.0]))
    assert (mode2[:, 0]).abs().max() < 0.3


def test_dominant_mode_mean_refuses_bad_starts_iters_and_bandwidths():
    x = torch.randn(2, 50, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    lw = torch.zeros(2, 50, dtype=torch.float64)
    # n_starts=0 was argmax's IndexError, a negative iters ran no iteration
    for name, bad in (("n_starts", 0), ("n_starts", 2.5), ("n_starts", True), ("iters", -1)):
        with pytest.raises(ConfigError, match=rf"{name} must be an integer >= \d, got"):
            dominant_mode_mean(x, lw, **{name: bad})
    # a negative or NaN bandwidth was silently replaced by 1
    for bad in (-1.0, 0.0, math.nan, math.inf, "1", True):
        with pytest.raises(ConfigError, match="bandwidth must be None, a finite number > 0"):
            dominant_mode_mean(x, lw, bandwidth=bad)
    for bad in (torch.tensor([1.0, -1.0, 1.0]), torch.full((2, 3), math.nan)):
        with pytest.raises(ConfigError, match=r"bandwidth must be finite and > 0"):
            dominant_mode_mean(x, lw, bandwidth=bad)
    # a (4,) bandwidth for D = 3 was torch's expand RuntimeError
    for bad in (torch.ones(4), torch.ones(3, 3), torch.ones(3, dtype=torch.bool)):
        with pytest.raises(ShapeError, match=r"bandwidth must be .* \(D,\) = \(3,\) or"):
            dominant_mode_mean(x, lw, bandwidth=bad)
    with pytest.raises(ConfigError, match="bandwidth must hold D = 3 numbers"):
        dominant_mode_mean(x, lw, bandwidth=[[1.0, 1.0], [1.0]])
    # every accepted form of one bandwidth gives the same estimate; 1 iteration and 1 start too
    ref = dominant_mode_mean(x, lw, bandwidth=0.5)
    same = [torch.tensor(0.5), torch.full((3,), 0.5), [0.5] * 3, torch.full((2, 3), 0.5)]
    for ok in same:
        torch.testing.assert_close(dominant_mode_mean(x, lw, bandwidth=ok), ref)
    assert dominant_mode_mean(x, lw, n_starts=1, iters=0).shape == (2, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_dominant_mode_mean_cuda_bandwidth_is_not_read_back_and_a_bad_one_gives_nan():
    x = torch.randn(2, 50, 3, dtype=torch.float64, device="cuda")
    lw = torch.zeros(2, 50, dtype=torch.float64, device="cuda")
    h = torch.tensor([1.0, -1.0, 1.0], device="cuda")
    assert torch.isnan(dominant_mode_mean(x, lw, bandwidth=h)).all()
    torch.testing.assert_close(
        dominant_mode_mean(x, lw, bandwidth=torch.ones(3, device="cuda")),
        dominant_mode_mean(x.cpu(), lw.cpu(), bandwidth=1.0).cuda(),
    )


def test_particle_set_and_shape_errors():
    x = torch.zeros(2, 3, 4)
    ps = ParticleSet.uniform(x)
    torch.testing.assert_close(ps.weights, torch.full((2, 3), 1 / 3))
    torch.testing.assert_close(ps.ess(), torch.tensor([3.0, 3.0]))
    assert ps.mean().shape == (2, 4)
    assert uniform_log_weights(x.double()).dtype == torch.float64
    with pytest.raises(ShapeError, match=r"states must be a \(B, N, D\) tensor"):
        ParticleSet(torch.zeros(3, 4), torch.zeros(3))
    with pytest.raises(ShapeError, match=r"log_weights must have shape \(B, N\) = \(2, 3\)"):
        ParticleSet(x, torch.zeros(2, 4))
    with pytest.raises(ShapeError, match="floating point"):
        ParticleSet(torch.zeros(2, 3, 4, dtype=torch.long), torch.zeros(2, 3))
    with pytest.raises(ShapeError, match="N >= 1"):
        ParticleSet(torch.zeros(2, 0, 4), torch.zeros(2, 0))


def test_has_nan_or_posinf_fast_path_edge_cases():
    from torchtrack.filter.particles import has_nan_or_posinf

    big = torch.full((4,), 3e38)  # float32 sum overflows to +inf: not an error
    assert not has_nan_or_posinf(big)
    assert not has_nan_or_posinf(torch.tensor([0.0, -math.inf]))
    assert has_nan_or_posinf(torch.tensor([math.inf, -math.inf]))  # sum is NaN
    assert has_nan_or_posinf(torch.tensor([1.0, math.inf]))
    assert has_nan_or_posinf(torch.tensor([1.0, math.nan]))


def test_uniform_log_weights_checks_the_states_like_the_rest_of_the_module():
    """Integer states gave log-weights of -1 for any N (-log N truncated), 2-D states (N, D)
    were read as N rows of D particles, and N = 0 was a bare 'math domain error'."""
    from torchtrack.filter.particles import uniform_log_weights

    ok = torch.zeros(2, 3, 4, dtype=torch.float64)
    assert uniform_log_weights(ok).tolist() == [[-math.log(3)] * 3] * 2
    with pytest.raises(ShapeError, match=r"states must be floating point .*got torch.int64"):
        uniform_log_weights(torch.zeros(1, 3, 2, dtype=torch.long))
    with pytest.raises(ShapeError, match=r"states must be a \(B, N, D\) tensor, got \(3, 2\)"):
        uniform_log_weights(torch.zeros(3, 2))
    with pytest.raises(ShapeError, match=r"at least one particle per batch row \(N >= 1\)"):
        uniform_log_weights(torch.zeros(1, 0, 2))


def test_best_particle_refuses_nan_log_weights():
    """A NaN log-weight was taken by argmax as the largest: its particle came back as the
    estimate, as the other estimators refuse NaN weights."""
    x = torch.arange(6.0).reshape(1, 3, 2)
    for bad in (math.nan, math.inf):
        with pytest.raises(FilterError, match="best_particle: log-weights contain NaN or"):
            best_particle(x, torch.tensor([[0.0, bad, -1.0]]))
    assert best_particle(x, torch.tensor([[-math.inf, -1.0, -math.inf]])).tolist() == [[2.0, 3.0]]
