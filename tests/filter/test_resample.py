import math

import pytest
import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
from torchtrack.filter.particles import ess
from torchtrack.filter.resample import RESAMPLERS, get_resampler, resample

SCHEMES = sorted(RESAMPLERS)


def _counts(anc: torch.Tensor, n: int) -> torch.Tensor:
    return torch.zeros(anc.shape[0], n, dtype=torch.float64).scatter_add_(
        1, anc, torch.ones_like(anc, dtype=torch.float64)
    )


@pytest.mark.parametrize("scheme", SCHEMES)
def test_unbiased_counts(scheme):
    # The batch axis doubles as repetitions: R rows with the same weights are R draws.
    n, r = 12, 20000
    g = torch.Generator().manual_seed(3)
    w = torch.softmax(torch.randn(n, generator=g, dtype=torch.float64) * 1.5, 0)
    anc = get_resampler(scheme)(w.expand(r, n), g)
    assert anc.shape == (r, n) and anc.dtype == torch.int64
    c = _counts(anc, n)
    assert (c.sum(1) == n).all()
    # Tolerance: 5 standard errors of the mean count under multinomial variance
    # N w (1 - w) / R (the other schemes have smaller variance), plus float slack.
    tol = 5 * torch.sqrt(n * w * (1 - w) / r) + 1e-9
    assert ((c.mean(0) - n * w).abs() <= tol).all(), (c.mean(0) - n * w).abs() / tol


def test_low_variance_schemes_beat_multinomial():
    n, r = 12, 20000
    g = torch.Generator().manual_seed(4)
    w = torch.softmax(torch.randn(n, generator=g, dtype=torch.float64), 0)
    var = {s: _counts(get_resampler(s)(w.expand(r, n), g), n).var(0).sum() for s in SCHEMES}
    theory = (n * w * (1 - w)).sum()  # multinomial
    assert abs(var["multinomial"] / theory - 1) < 0.05
    for s in ("systematic", "stratified", "residual"):
        assert var[s] < 0.7 * var["multinomial"], (s, var)
    # Systematic counts are floor(Nw) or ceil(Nw): variance at most 1/4 per particle.
    assert var["systematic"] <= 0.25 * n


def test_residual_keeps_deterministic_copies():
    g = torch.Generator().manual_seed(5)
    w = torch.softmax(torch.randn(50, 30, generator=g, dtype=torch.float64) * 2, 1)
    c = _counts(get_resampler("residual")(w, g), 30)
    assert (c >= torch.floor(30 * w)).all()


@pytest.mark.parametrize("scheme", SCHEMES)
def test_degenerate_and_float32_large_n(scheme):
    fn = get_resampler(scheme)
    w = torch.zeros(2, 7)
    w[0, 3] = 1.0
    w[1, 6] = 1.0
    anc = fn(w, torch.Generator().manual_seed(0))
    assert (anc[0] == 3).all() and (anc[1] == 6).all()
    # float32 weights, N = 10^6: mass of the last particle is not lost to rounding.
    n = 10**6
    w = torch.full((1, n), 1.0 / n, dtype=torch.float32)
    anc = fn(w, torch.Generator().manual_seed(0))
    assert anc.min() >= 0 and anc.max() < n
    assert _counts(anc, n).max() <= (1 if scheme in ("systematic", "residual") else 20)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_n_out_draws_other_counts(scheme):
    g = torch.Generator().manual_seed(6)
    w = torch.softmax(torch.randn(4, 30, generator=g), 1)
    anc = get_resampler(scheme)(w, g, 10)
    assert anc.shape == (4, 10) and anc.max() < 30


def test_registry_names_valid_choices():
    with pytest.raises(
        ConfigError,
        match="unknown resampling scheme 'sytematic'; valid: multinomial, residual, stratified, systematic",
    ):
        get_resampler("sytematic")
    with pytest.raises(ConfigError, match="valid: multinomial"):
        resample(torch.zeros(1, 3), scheme="bogus")
    with pytest.raises(ConfigError, match=r"ess_fraction must be None or in \(0, 1\]"):
        resample(torch.zeros(1, 3), ess_fraction=1.5)
    with pytest.raises(ShapeError, match=r"weights must be a \(B, N\) tensor"):
        get_resampler("systematic")(torch.ones(3))
    for scheme in SCHEMES:
        with pytest.raises(FilterError, match="positive finite sum in every row"):
            get_resampler(scheme)(torch.zeros(2, 5))
    with pytest.raises(FilterError, match="resample: log-weights contain NaN"):
        resample(torch.tensor([[0.0, float("nan")]]))


def test_threshold_resamples_only_low_ess_rows():
    n = 100
    lw = torch.zeros(3, n, dtype=torch.float64)
    lw[1] = torch.linspace(0, 30, n)  # degenerate row: ESS ~ 3
    lw[2] = torch.linspace(0, 0.5, n)  # nearly uniform: ESS close to N
    assert ess(lw)[1] < 50 < ess(lw)[2]
    anc, new_lw, done = resample(lw, "systematic", 0.5, torch.Generator().manual_seed(0))
    assert done.tolist() == [False, True, False]
    assert (anc[0] == torch.arange(n)).all() and (anc[2] == torch.arange(n)).all()
    torch.testing.assert_close(new_lw[2], lw[2] - torch.logsumexp(lw[2], 0))
    torch.testing.assert_close(new_lw[1], torch.full((n,), -math.log(n), dtype=torch.float64))
    anc, _, done = resample(lw, "multinomial", None, torch.Generator().manual_seed(0))
    assert done.all()


@pytest.mark.parametrize("scheme", SCHEMES)
def test_batch_equals_single_runs_with_same_generators(scheme):
    w = torch.softmax(torch.randn(5, 40, generator=torch.Generator().manual_seed(7)), 1)
    gens = [torch.Generator().manual_seed(100 + b) for b in range(5)]
    batch = get_resampler(scheme)(w, gens)
    for b in range(5):
        single = get_resampler(scheme)(w[b : b + 1], torch.Generator().manual_seed(100 + b))
        assert torch.equal(batch[b : b + 1], single)
    with pytest.raises(ConfigError, match="sequence of B=5 generators"):
        get_resampler(scheme)(w, gens[:2])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
@pytest.mark.parametrize("scheme", SCHEMES)
def test_cuda_device_follows_input(scheme):
    w = torch.softmax(torch.randn(3, 50, device="cuda"), 1)
    anc = get_resampler(scheme)(w, torch.Generator(device="cuda").manual_seed(0))
    assert anc.device.type == "cuda" and anc.shape == (3, 50)
