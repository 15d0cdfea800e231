import math

import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, FilterError, ShapeError
from torchtrack.filter.particles import ess
from torchtrack.filter.resample import (
    _STEPS,
    RESAMPLERS,
    _cdf,
    _count_below,
    _merge_below,
    _sorted_uniforms,
    get_resampler,
    resample,
)

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


def test_residual_variance_is_multinomial_on_the_residuals():
    # Var(n_i) = r p_i (1 - p_i): r multinomial draws with probabilities p_i = residual_i / r.
    n, reps = 12, 20000
    g = torch.Generator().manual_seed(8)
    w = torch.softmax(torch.randn(n, generator=g, dtype=torch.float64), 0)
    rest = n * w - torch.floor(n * w)
    r = rest.sum()
    p = rest / r
    c = _counts(get_resampler("residual")(w.expand(reps, n), g), n)
    torch.testing.assert_close(c.mean(0), n * w, atol=0.03, rtol=0)
    assert abs(c.var(0).sum() / (r * p * (1 - p)).sum() - 1) < 0.05


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
    for bad in ("0.5", True, math.nan, torch.tensor(0.5)):  # "0.5" and True went through float()
        with pytest.raises(
            ConfigError, match=r"ess_fraction must be None or in \(0, 1\] \(a number"
        ):
            resample(torch.zeros(1, 3), ess_fraction=bad)
    assert resample(torch.zeros(1, 3), ess_fraction=np.float32(0.5))[2].tolist() == [False]
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


def _uniform_rows(rows: list[list[float]], length: int) -> torch.Tensor:
    """``_sorted_uniforms``' layout for given sorted rows: each padded to ``length - 1`` values
    with the sentinel ``length``, then the sentinel ``length`` once more, then the padding."""
    flat = [v for r in rows for v in r + [float(length)] * (length - len(r))]
    return torch.tensor(flat + [float(length)] * _STEPS, dtype=torch.float64)


def test_count_below_equals_searchsorted():
    # The merge through unit bins against the obvious reference, on rows built to hit every
    # path: empty and crowded bins (19 uniforms in bin 5: more than _STEPS plus a full window of
    # steps), CDF values equal to uniforms and to bin edges, zero-weight runs, the last bin.
    g = torch.Generator().manual_seed(0)
    crowded = sorted((5 + torch.rand(19, generator=g, dtype=torch.float64)).tolist())
    rows = [
        [0.5, 1.0, 1.25, 3.0, *crowded, 7.5, 9.99],
        [0.0, 0.1, 0.2, 0.3, 2.0, 2.0, 9.0],
        [],
    ]
    length = 30
    u = _uniform_rows(rows, length)
    cdf = torch.tensor(
        [
            [0.0, 0.5, 0.75, 1.0, 1.0, 3.0, 5.0, crowded[3], crowded[-1], 5.999, 6.0, 29.0],
            [0.0, 0.0, 0.05, 2.0, 2.0, 2.5, 8.99, 9.0, 9.5, 10.0, 10.0, 29.5],
            [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0],
        ],
        dtype=torch.float64,
    )
    s = u[: 3 * length].view(3, length)
    ref = torch.searchsorted(s, cdf, right=False) + torch.arange(3).unsqueeze(1) * length
    for count_below in (_merge_below, _count_below):
        assert torch.equal(count_below(u, 3, cdf).view(3, -1).long(), ref)
        for b in range(3):  # each row alone: the single-row path
            one = _uniform_rows([rows[b]], length)
            got = count_below(one, 1, cdf[b : b + 1]).long()
            assert torch.equal(got, torch.searchsorted(s[b], cdf[b], right=False))


@pytest.mark.parametrize("b", [1, 4])
def test_count_below_random_merges(b):
    g = torch.Generator().manual_seed(11)
    for n in (1, 7, 300):
        w = torch.rand(b, n, generator=g, dtype=torch.float64) ** 6
        w[:, : n // 3] = 0  # leading zero weights: runs of equal CDF values
        w[:, -1] += 1e-3
        count = torch.randint(0, n + 1, (b,), generator=g)
        for k, cnt, top in ((n, None, None), (int(count.max()), count, count.double())):
            u = _sorted_uniforms(b, k, g, w.device, count=cnt, top=top)
            cdf = _cdf(w, k) if cnt is None else _cdf(w, 1.0) * top.unsqueeze(1)
            s = u[: b * (k + 1)].view(b, k + 1)
            ref = torch.searchsorted(s, cdf, right=False)
            ref += torch.arange(b).unsqueeze(1) * (k + 1)
            for count_below in (_merge_below, _count_below):
                assert torch.equal(count_below(u, b, cdf).view(b, -1).long(), ref)


def test_sorted_uniforms_are_sorted_uniform_draws():
    # Rows sorted, in [0, top), count[b] of them, then sentinels; pooled values uniform.
    g = torch.Generator().manual_seed(12)
    b, k = 400, 50
    count = torch.randint(0, k + 1, (b,), generator=g)
    top = torch.rand(b, generator=g, dtype=torch.float64) * k
    u = _sorted_uniforms(b, k, g, torch.device("cpu"), count=count, top=top)
    s = u[: b * (k + 1)].view(b, k + 1)
    real = torch.arange(k + 1).unsqueeze(0) < count.unsqueeze(1)
    assert (s[~real] == k + 1).all() and (u[b * (k + 1) :] == k + 1).all()
    assert (s.diff(dim=1) >= 0).all()
    x = (s / top.unsqueeze(1))[real].sort().values  # pooled: i.i.d. uniform on [0, 1)
    assert x.min() >= 0 and x.max() < 1
    ks = (x - torch.arange(1, x.numel() + 1, dtype=torch.float64) / x.numel()).abs().max()
    assert ks < 1.63 / math.sqrt(x.numel())  # Kolmogorov-Smirnov, 1 % level
    u = _sorted_uniforms(3, k, g, torch.device("cpu"))  # count None: k per row on [0, k)
    s = u[: 3 * (k + 1)].view(3, k + 1)
    assert (s[:, :k] < k).all() and (s[:, k] == k + 1).all() and (s.diff(dim=1) > 0).all()


def test_multinomial_and_residual_equal_the_inverse_cdf_of_their_uniforms():
    # Reference: inverse CDF by binary search on the same uniforms (same generator state).
    w = torch.softmax(torch.randn(3, 500, generator=torch.Generator().manual_seed(9)) * 3, 1)
    wd = w.double()
    u = _sorted_uniforms(3, 500, torch.Generator().manual_seed(1), w.device)
    s = u[: 3 * 501].view(3, 501)[:, :500].contiguous()
    ref = torch.searchsorted(_cdf(w, 500), s, right=True)
    assert torch.equal(get_resampler("multinomial")(w, torch.Generator().manual_seed(1)), ref)
    for b in range(3):  # residual: floor(M w) copies, then r draws on the residual CDF
        nw = 500 * wd[b] / wd[b].sum()
        floor = nw.floor().long()
        r = 500 - int(floor.sum())
        rest = (nw - nw.floor()).cumsum(0)
        gen = torch.Generator().manual_seed(2)
        u = _sorted_uniforms(1, r, gen, w.device, torch.tensor([r]), rest[-1:])[:r]
        ref = torch.cat(
            [torch.arange(500).repeat_interleave(floor), torch.searchsorted(rest, u, right=True)]
        )
        got = get_resampler("residual")(w[b : b + 1], torch.Generator().manual_seed(2))
        assert torch.equal(got[0], ref.sort().values)


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("n", [60, 3000])
def test_zero_weights_never_drawn_in_a_batch(scheme, n):
    # Zero-weight particles (leading, interleaved, trailing) get no offspring in any row of a
    # batch, and the batch still equals single runs (per-row generators), also with M != N.
    # With n = 3000 the batch (12000 values) takes the merge, each row alone the search.
    w = torch.rand(4, n, generator=torch.Generator().manual_seed(10))
    w[:, :7] = 0
    w[:, 20::2] = 0
    w[:, -5:] = 0
    w[2] = 0
    w[2, 30] = 1.0  # one particle carries all the mass
    for n_out in (None, n // 2 + 7):
        gens = [torch.Generator().manual_seed(200 + b) for b in range(4)]
        anc = get_resampler(scheme)(w, gens, n_out)
        assert (torch.gather(w, 1, anc) > 0).all()
        assert (anc[2] == 30).all()
        for b in range(4):
            one = get_resampler(scheme)(w[b : b + 1], torch.Generator().manual_seed(200 + b), n_out)
            assert torch.equal(anc[b : b + 1], one)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_negative_weights_and_empty_batches(scheme):
    fn = get_resampler(scheme)
    with pytest.raises(FilterError, match="must be non-negative"):
        fn(torch.tensor([[0.5, -0.1, 0.6]]))
    assert fn(torch.zeros(0, 5)).shape == (0, 5)
    assert fn(torch.zeros(0, 5), None, 3).shape == (0, 3)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_n_out_that_is_not_a_positive_integer_is_refused(scheme):
    """n_out -3 raised torch's RuntimeError, 0 an IndexError (stratified) or no particle, and
    2.5 silently drew 2."""
    fn = get_resampler(scheme)
    for bad in (-3, 0, 2.5, True, "4"):
        with pytest.raises(ConfigError, match=r"n_out must be None or an integer >= 1"):
            fn(torch.ones(2, 5), None, bad)
    assert fn(torch.ones(2, 5), None, np.int64(3)).shape == (2, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
@pytest.mark.parametrize("scheme", SCHEMES)
def test_cuda_device_follows_input(scheme):
    w = torch.softmax(torch.randn(3, 50, device="cuda"), 1)
    anc = get_resampler(scheme)(w, torch.Generator(device="cuda").manual_seed(0))
    assert anc.device.type == "cuda" and anc.shape == (3, 50)
    # the offspring histogram is a scatter-add off the CPU: ancestors still sorted, in range
    assert bool((anc[:, 1:] >= anc[:, :-1]).all()) and 0 <= int(anc.min()) <= int(anc.max()) < 50
    with pytest.raises(FilterError, match="must be non-negative"):
        get_resampler(scheme)(torch.tensor([[0.5, -0.1, 0.6]], device="cuda"))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA not available")
def test_cuda_histogram_is_bincount():
    from torchtrack.filter.resample import _histogram

    x = torch.randint(0, 40, (5000,), generator=torch.Generator().manual_seed(0))
    assert torch.equal(_histogram(x.cuda(), 50).cpu(), _histogram(x, 50))
    assert torch.equal(_histogram(x, 50), torch.bincount(x, minlength=50))


def test_random_helpers_draw_torchs_numbers_on_the_cpu():
    """``filter._random``'s randperm / randint / rand / multinomial give torch's own draws for a generator of
    the tensors' device (the cross-device path runs in tests/test_devices.py on a GPU)."""
    from torchtrack.filter import _random

    def gen():
        return torch.Generator().manual_seed(3)

    assert torch.equal(_random.randperm(17, gen(), "cpu"), torch.randperm(17, generator=gen()))
    assert torch.equal(
        _random.randint(2, 9, (4, 5), gen(), "cpu"), torch.randint(2, 9, (4, 5), generator=gen())
    )
    got = _random.rand((3, 4), gen(), torch.float64, torch.device("cpu"))
    assert torch.equal(got, torch.rand((3, 4), generator=gen(), dtype=torch.float64))
    w = torch.rand(40, generator=gen(), dtype=torch.float64)
    assert torch.equal(
        _random.multinomial(w, 25, gen(), replacement=True),
        torch.multinomial(w, 25, replacement=True, generator=gen()),
    )
    assert _random.randperm(5, None).device.type == "cpu"


def test_a_generator_that_is_no_generator_or_sequence_of_generators_is_refused():
    """generator=5 was 'int' object is not iterable, a string was taken as a 'sequence of 4'
    generators and [None] reached torch: the message names what a generator may be."""
    from torchtrack.errors import ConfigError
    from torchtrack.filter.resample import systematic

    w = torch.tensor([[0.2, 0.3, 0.5]])
    for bad, what in ((5, "int 5"), ("abc", "str 'abc'"), ([None], r"a sequence holding NoneType")):
        with pytest.raises(
            ConfigError,
            match=rf"generator must be None, a torch.Generator or a sequence of torch.Generator .*got {what}",
        ):
            systematic(w, bad)
    systematic(w, [torch.Generator()])
