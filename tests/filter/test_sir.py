import math

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
from torchtrack.filter.motion import KleinAR
from torchtrack.filter.particles import uniform_log_weights
from torchtrack.filter.resample import RESAMPLERS
from torchtrack.filter.seir import seir_step
from torchtrack.filter.sir import sir_step

# Linear-Gaussian model: x = (position, velocity), y = position + noise.
F = torch.tensor([[1.0, 1.0], [0.0, 1.0]], dtype=torch.float64)
Q = torch.tensor([[0.5, 0.1], [0.1, 0.2]], dtype=torch.float64)
R = 1.0
M0 = torch.tensor([0.0, 1.0], dtype=torch.float64)
P0 = torch.tensor([[4.0, 0.0], [0.0, 1.0]], dtype=torch.float64)


def kalman(ys):
    """Reference Kalman filter (predict, then update on each y); returns means and covariances."""
    m, p = M0.clone(), P0.clone()
    h = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    means, covs = [], []
    for y in ys:
        m, p = F @ m, F @ p @ F.T + Q
        s = h @ p @ h.T + R
        k = p @ h.T / s
        m = m + (k * (y - h @ m)).flatten()
        p = (torch.eye(2, dtype=torch.float64) - k @ h) @ p
        means.append(m.clone())
        covs.append(p.clone())
    return means, covs


class LinearMotion:
    def __init__(self):
        self.L = torch.linalg.cholesky(Q)

    def __call__(self, states, generator=None):
        e = torch.randn(states.shape, generator=generator, dtype=states.dtype)
        return states @ F.T + e @ self.L.T


def _simulate_obs(t, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = M0 + torch.linalg.cholesky(P0) @ torch.randn(2, generator=g, dtype=torch.float64)
    ys = []
    for _ in range(t):
        x = F @ x + torch.linalg.cholesky(Q) @ torch.randn(2, generator=g, dtype=torch.float64)
        ys.append(float(x[0] + math.sqrt(R) * torch.randn(1, generator=g, dtype=torch.float64)))
    return ys


def _run_pf(ys, n, reps, scheme, seed):
    g = torch.Generator().manual_seed(seed)
    x = M0 + torch.randn(reps, n, 2, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(P0).T
    lw = uniform_log_weights(x)
    motion = LinearMotion()
    for y in ys:

        def lik(s, y=y):
            return -0.5 * (s[..., 0] - y) ** 2 / R

        r = sir_step(x, lw, motion, lik, scheme=scheme, generator=g)
        x, lw = r.states, r.log_weights
    w = lw.exp()
    mean = torch.einsum("bn,bnd->bd", w, x)
    var = torch.einsum("bn,bnd->bd", w, (x - mean.unsqueeze(1)) ** 2)
    return mean, var


@pytest.mark.parametrize("scheme", ["systematic", "multinomial"])
def test_pf_converges_to_kalman_as_n_grows(scheme):
    ys = _simulate_obs(8)
    means, covs = kalman(ys)
    kf_mean, kf_var = means[-1], torch.diagonal(covs[-1])
    mse = {}
    for n in (50, 500, 5000):
        mean, var = _run_pf(ys, n, reps=40, scheme=scheme, seed=n)
        mse[n] = ((mean - kf_mean) ** 2).sum(1).mean().item()
        if n == 5000:
            # Posterior variance within 10 % and mean within a small fraction of the KF std.
            assert ((var.mean(0) / kf_var - 1).abs() < 0.1).all(), (var.mean(0), kf_var)
            assert ((mean.mean(0) - kf_mean).abs() < 0.05 * kf_var.sqrt()).all()
    # Monte Carlo error ~ 1/N: a 100x larger N must cut the squared error at least 20x.
    assert mse[5000] < mse[50] / 20, mse
    assert mse[500] < mse[50] / 3, mse


def _targets():
    return torch.tensor([[60.0, 40.0], [30.0, 90.0], [100.0, 100.0]], dtype=torch.float64)


def _row_lik(targets):
    def lik(s):
        return -0.5 * ((s[..., :2] - targets.unsqueeze(1)) ** 2).sum(-1) / 25.0

    return lik


@pytest.mark.parametrize("scheme", sorted(RESAMPLERS))
@pytest.mark.parametrize("step", ["sir", "seir"])
def test_batch_equals_single_runs_with_same_generators(scheme, step):
    boxes = torch.tensor(
        [[40.0, 30.0, 20.0, 30.0], [20.0, 70.0, 10.0, 20.0], [90.0, 95.0, 12.0, 12.0]],
        dtype=torch.float64,
    )
    m = KleinAR()
    targets = _targets()

    def run(rows, gens):
        x = m.init(boxes[rows], 200, gens)
        lw = uniform_log_weights(x)
        out = []
        for _ in range(3):
            if step == "sir":
                r = sir_step(
                    x,
                    lw,
                    m,
                    _row_lik(targets[rows]),
                    scheme=scheme,
                    ess_fraction=0.5,
                    generator=gens,
                )
            else:
                r = seir_step(
                    x,
                    lw,
                    m,
                    _row_lik(targets[rows]),
                    scheme=scheme,
                    mutation_std=2.0,
                    generator=gens,
                )
            x, lw = r.states, r.log_weights
            out.append(r)
        return out

    batch = run(slice(0, 3), [torch.Generator().manual_seed(10 + b) for b in range(3)])
    for b in range(3):
        single = run(slice(b, b + 1), torch.Generator().manual_seed(10 + b))
        for rb, rs in zip(batch, single, strict=True):
            torch.testing.assert_close(rb.states[b : b + 1], rs.states, rtol=1e-12, atol=1e-9)
            torch.testing.assert_close(
                rb.log_weights[b : b + 1], rs.log_weights, rtol=1e-12, atol=1e-12
            )
            torch.testing.assert_close(rb.estimate[b : b + 1], rs.estimate, rtol=1e-12, atol=1e-9)
            assert torch.equal(rb.ancestors[b : b + 1], rs.ancestors)
            assert torch.equal(rb.iterations[b : b + 1], rs.iterations)


@pytest.mark.parametrize("step", [sir_step, seir_step])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_all_zero_likelihood_recovers_uniform_never_nan(step, dtype):
    m = KleinAR()
    g = torch.Generator().manual_seed(0)
    x = m.init(torch.tensor([[10.0, 10.0, 5.0, 5.0]] * 2, dtype=dtype), 50, g)
    lw = uniform_log_weights(x)

    def lik(s):  # row 0: every likelihood is zero; row 1: ordinary
        out = torch.exp(-0.5 * ((s[..., 0] - 12.5) / 3) ** 2)
        out[0] = 0.0
        return out

    r = step(x, lw, m, lik, log_likelihood=False, generator=g)
    assert r.recovered.tolist() == [True, False]
    assert r.states.dtype == dtype and r.log_weights.dtype == dtype
    torch.testing.assert_close(r.log_weights[0], torch.full((50,), -math.log(50), dtype=dtype))
    torch.testing.assert_close(r.estimate[0], r.states[0].mean(0))
    assert r.log_evidence[0] == -math.inf and torch.isfinite(r.log_evidence[1])
    for t in (r.states, r.log_weights, r.estimate, r.ess):
        assert not torch.isnan(t).any()
    # all log-weights -inf on input: the resampler restarts them uniform, no NaN
    lw_dead = torch.full_like(lw, -math.inf)
    r2 = step(x, lw_dead, m, lambda s: torch.zeros(s.shape[:2], dtype=dtype), generator=g)
    assert not torch.isnan(r2.states).any() and not r2.recovered.any()


@pytest.mark.parametrize("step,name", [(sir_step, "sir_step"), (seir_step, "seir_step")])
def test_states_that_are_not_finite_after_the_motion_raise_naming_step(step, name):
    """NaN states given, or made by the motion model, gave NaN estimates with no error (a
    likelihood that scores NaN states 0 hides them)."""
    x = torch.zeros(3, 20, 4, dtype=torch.float64)
    lw = uniform_log_weights(x)
    flat = lambda s: torch.zeros(s.shape[:2], dtype=s.dtype)  # noqa: E731
    still = lambda s, g: s  # noqa: E731
    bad = x.clone()
    bad[1, 5, 2] = math.nan
    with pytest.raises(FilterError, match=rf"{name}: the particles after the motion .*\[1\]"):
        step(bad, lw, still, flat)
    for v in (math.nan, math.inf):
        with pytest.raises(FilterError, match=rf"{name}: .* NaN or infinite .*\[0, 1, 2\]"):
            step(x, lw, lambda s, g, v=v: s + v, flat)
    huge = torch.full_like(x, 1e307)  # finite, though the check's sum overflows
    assert torch.isfinite(step(huge, lw, still, flat).estimate).all()


@pytest.mark.parametrize("step,name", [(sir_step, "sir_step"), (seir_step, "seir_step")])
def test_bad_likelihood_raises_naming_step(step, name):
    m = KleinAR()
    x = m.init(torch.tensor([[10.0, 10.0, 5.0, 5.0]]), 20, torch.Generator().manual_seed(0))
    lw = uniform_log_weights(x)

    def nan_lik(s):
        out = torch.zeros(s.shape[:2])
        out[0, 3] = math.nan
        return out

    with pytest.raises(FilterError, match=f"{name}: likelihood returned NaN"):
        step(x, lw, m, nan_lik)
    with pytest.raises(FilterError, match=f"{name}: likelihood must be finite and >= 0"):
        step(x, lw, m, lambda s: -torch.ones(s.shape[:2]), log_likelihood=False)
    with pytest.raises(FilterError, match=rf"{name}: log-likelihood returned \+inf"):
        step(x, lw, m, lambda s: torch.full(s.shape[:2], math.inf))
    with pytest.raises(ShapeError, match=rf"{name}: likelihood must return \(B, M\) = \(1, 20\)"):
        step(x, lw, m, lambda s: torch.zeros(s.shape[1]))
    with pytest.raises(ConfigError, match="unknown estimator 'median'; valid: best, mean, mode"):
        step(x, lw, m, lambda s: torch.zeros(s.shape[:2]), estimator="median")
    with pytest.raises(ConfigError, match="valid: multinomial, residual, stratified, systematic"):
        step(x, lw, m, lambda s: torch.zeros(s.shape[:2]), scheme="nope")


def test_seir_reaches_higher_ess_than_sir_on_peaked_likelihood():
    g = torch.Generator().manual_seed(5)
    b, n = 16, 400
    x = torch.randn(b, n, 2, generator=g, dtype=torch.float64) * 10.0
    lw = uniform_log_weights(x)
    target = torch.randn(b, 2, generator=g, dtype=torch.float64) * 5.0

    def lik(s):  # sharply peaked: std 0.5 against a prior spread of ~10
        return -0.5 * ((s - target.unsqueeze(1)) ** 2).sum(-1) / 0.25

    def motion(s, generator=None):
        return s + torch.randn(s.shape, generator=generator, dtype=s.dtype)

    sir = sir_step(x, lw, motion, lik, generator=g)
    seir = seir_step(x, lw, motion, lik, ess_target=0.5, max_iter=10, mutation_std=0.5, generator=g)
    assert sir.ess.mean() < 10
    assert seir.ess.mean() > 5 * sir.ess.mean(), (seir.ess.mean(), sir.ess.mean())
    assert (seir.iterations >= 1).all()
    # ... and its estimate is at least as close to the likelihood peak on average
    err_sir = (sir.estimate - target).norm(dim=1).mean()
    err_seir = (seir.estimate - target).norm(dim=1).mean()
    assert err_seir <= err_sir * 1.2


def test_seir_config_errors():
    x = torch.zeros(1, 5, 2)
    lw = uniform_log_weights(x)
    with pytest.raises(ConfigError, match=r"ess_target must be in \(0, 1\]"):
        seir_step(x, lw, lambda s, g: s, lambda s: torch.zeros(s.shape[:2]), ess_target=0)
    with pytest.raises(ConfigError, match="max_iter must be >= 0"):
        seir_step(x, lw, lambda s, g: s, lambda s: torch.zeros(s.shape[:2]), max_iter=-1)
    with pytest.raises(ConfigError, match=r"mutation_std must be a float or a \(2,\) tensor"):
        seir_step(
            x, lw, lambda s, g: s, lambda s: torch.zeros(s.shape[:2]), mutation_std=torch.ones(3)
        )


def test_estimators_and_resample_flags():
    m = KleinAR()
    g = torch.Generator().manual_seed(1)
    x = m.init(torch.tensor([[10.0, 10.0, 5.0, 5.0]] * 2, dtype=torch.float64), 100, g)
    lw = uniform_log_weights(x)
    lik = _row_lik(torch.tensor([[14.0, 12.0], [10.0, 16.0]], dtype=torch.float64))
    for est in ("mean", "best", "mode"):
        r = sir_step(x, lw, m, lik, estimator=est, ess_fraction=0.5, generator=g)
        assert r.estimate.shape == (2, 6) and torch.isfinite(r.estimate).all()
        # uniform input weights: ESS = N, so no row is resampled under a threshold
        assert not r.resampled.any() and (r.ancestors == torch.arange(100)).all()
        assert (r.iterations == 0).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
@pytest.mark.parametrize("step", [sir_step, seir_step])
def test_cuda_step_device_follows_input(step):
    m = KleinAR()
    g = torch.Generator(device="cuda").manual_seed(0)
    x = m.init(torch.tensor([[10.0, 10.0, 5.0, 5.0]] * 3, device="cuda"), 100, g)
    r = step(x, uniform_log_weights(x), m, lambda s: -((s[..., 0] - 12.0) ** 2), generator=g)
    assert r.states.device.type == "cuda" and r.estimate.device.type == "cuda"
    assert not torch.isnan(r.states).any()


def test_results_independent_of_thread_count():
    m = KleinAR()
    lik = _row_lik(_targets())
    boxes = torch.tensor([[40.0, 30.0, 20.0, 30.0]] * 3, dtype=torch.float64)
    before = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            g = torch.Generator().manual_seed(0)
            x = m.init(boxes, 20_000, g)
            r = sir_step(x, uniform_log_weights(x), m, lik, generator=g)
            r = sir_step(r.states, r.log_weights, m, lik, scheme="residual", generator=g)
            out.append(r)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(out[0].ancestors, out[1].ancestors)
    torch.testing.assert_close(out[0].states, out[1].states, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(out[0].estimate, out[1].estimate, rtol=1e-12, atol=1e-9)


def test_seir_rows_with_different_iteration_counts_match_single_runs():
    # Row 0: broad likelihood (no evolution needed); rows 1, 2: sharp (several rounds).
    g0 = torch.Generator().manual_seed(3)
    x0 = torch.randn(3, 300, 2, generator=g0, dtype=torch.float64) * 10.0
    target = torch.tensor([[0.0, 0.0], [3.0, -2.0], [-5.0, 4.0]], dtype=torch.float64)
    scale = torch.tensor([100.0, 0.3, 0.6], dtype=torch.float64)

    def make_lik(rows):
        def lik(s):
            d2 = ((s - target[rows].unsqueeze(1)) ** 2).sum(-1)
            return -0.5 * d2 / scale[rows].unsqueeze(1) ** 2

        return lik

    def motion(s, generator=None):
        if generator is None or isinstance(generator, torch.Generator):
            return s + torch.randn(s.shape, generator=generator, dtype=s.dtype)
        return s + torch.stack(
            [torch.randn(s.shape[1:], generator=g, dtype=s.dtype) for g in generator]
        )

    def run(rows, gens):
        x, lw = x0[rows], uniform_log_weights(x0[rows])
        out = []
        for _ in range(2):
            r = seir_step(
                x,
                lw,
                motion,
                make_lik(rows),
                ess_target=0.6,
                max_iter=6,
                mutation_std=0.3,
                generator=gens,
            )
            x, lw = r.states, r.log_weights
            out.append(r)
        return out

    batch = run(slice(0, 3), [torch.Generator().manual_seed(20 + b) for b in range(3)])
    assert len(set(batch[0].iterations.tolist())) > 1, batch[0].iterations
    for b in range(3):
        single = run(slice(b, b + 1), [torch.Generator().manual_seed(20 + b)])
        for rb, rs in zip(batch, single, strict=True):
            assert torch.equal(rb.iterations[b : b + 1], rs.iterations)
            torch.testing.assert_close(rb.states[b : b + 1], rs.states, rtol=1e-12, atol=1e-9)
            assert torch.equal(rb.ancestors[b : b + 1], rs.ancestors)


def test_seir_ancestors_follow_copies_and_mutations():
    n = 200
    x0 = torch.arange(n, dtype=torch.float64).view(1, n, 1).repeat(2, 1, 1)  # distinct integers

    def lik(s):
        return -0.5 * (s[..., 0] - 120.0) ** 2 / 4.0

    r = seir_step(
        x0,
        uniform_log_weights(x0),
        lambda s, g: s,  # identity motion: predicted particle j is input particle ancestors[j]
        lik,
        ess_target=0.9,
        max_iter=4,
        mutation_std=0.0,  # a mutation child equals its parent
        generator=torch.Generator().manual_seed(0),
    )
    assert (r.iterations >= 1).all()
    assert r.ancestors.min() >= 0 and r.ancestors.max() < n
    vals = r.states[..., 0]
    exact = vals == vals.round()  # copies and mutations (crossovers are almost never integers)
    assert exact.sum() > 0
    torch.testing.assert_close(vals[exact], x0[..., 0].gather(1, r.ancestors)[exact])


def test_seir_refuses_bool_and_odd_numbers_for_its_settings():
    """ess_target=True was a target of 1, max_iter=True / 2.5 ran 1 / 2 rounds, a NaN
    mutation_std was reported as 'likelihood returned NaN', '1' was torch's TypeError and a
    negative one was taken as its absolute value."""
    x = torch.zeros(1, 5, 2)
    lw = uniform_log_weights(x)

    def step(**kw):
        return seir_step(x, lw, lambda s, g: s, lambda s: torch.zeros(s.shape[:2]), **kw)

    with pytest.raises(ConfigError, match=r"ess_target must be in \(0, 1\] \(a number\)"):
        step(ess_target=True)
    for bad in (True, 2.5):
        with pytest.raises(ConfigError, match=r"max_iter must be >= 0 \(an integer\)"):
            step(max_iter=bad)
    for bad in (math.nan, -1.0, "1", True, torch.tensor([1.0, math.nan])):
        with pytest.raises(ConfigError, match="mutation_std must be a finite number >= 0"):
            step(mutation_std=bad)
    step(mutation_std=torch.tensor([1.0, 0.0]), max_iter=np.int64(2))  # numpy integers taken


@pytest.mark.parametrize("dtype", [torch.bool, torch.complex64])
def test_likelihood_of_bools_or_complex_numbers_is_refused(dtype):
    """A bool likelihood was read as log-likelihoods 0 / 1, a complex one lost its imaginary
    part with only torch's warning; both were filtered without a word."""
    x = torch.zeros(1, 5, 2)
    with pytest.raises(ShapeError, match="sir_step: likelihood must return real numbers, got"):
        sir_step(
            x,
            uniform_log_weights(x),
            lambda s, g: s,
            lambda s: torch.ones(s.shape[:2], dtype=dtype),
        )
