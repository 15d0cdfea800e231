"""HaarBoxLikelihood: features against direct pixel sums, chunking, the compiled path, errors."""

from __future__ import annotations

import pytest
import torch
from torch.nn import functional as F

import torchtrack.observe.haar_box as hb
from torchtrack.errors import ConfigError, ShapeError
from torchtrack.features.integral import integral_image
from torchtrack.filter import KleinAR, sir_step, uniform_log_weights
from torchtrack.observe.haar_box import HaarBoxFeatures, HaarBoxLikelihood


def _frame(h=37, w=53, seed=0):
    g = torch.Generator().manual_seed(seed)
    img = torch.randint(0, 256, (h, w), generator=g).to(torch.float64)
    img = img - img.mean()
    return img, integral_image(img[None, None])[0, 0]


def _reference(img, feats, box):
    """Features of one box from direct pixel sums (Python rounding, clamped corners)."""
    h, w = img.shape
    bx, by, bw, bh = box
    out = []
    for i in range(len(feats)):
        s3, s2 = feats.split[i].tolist(), feats.span[i].tolist()
        if i < feats.n_horizontal:
            xs = [min(max(round(bx + a * bw), 0), w) for a in s3]
            ys = [min(max(round(by + a * bh), 0), h) for a in s2]
            v = img[ys[0] : ys[1], xs[0] : xs[1]].sum() - img[ys[0] : ys[1], xs[1] : xs[2]].sum()
        else:
            ys = [min(max(round(by + a * bh), 0), h) for a in s3]
            xs = [min(max(round(bx + a * bw), 0), w) for a in s2]
            v = img[ys[0] : ys[1], xs[0] : xs[1]].sum() - img[ys[1] : ys[2], xs[0] : xs[1]].sum()
        out.append(float(v) / max(bw * bh, 1.0))
    return torch.tensor(out, dtype=torch.float64)


def _boxes(n, h, w, seed=1):
    g = torch.Generator().manual_seed(seed)
    wh = torch.rand(n, 2, generator=g) * torch.tensor([w * 0.8, h * 0.8]) + 2
    # some boxes reach outside the frame: their corners are clamped
    xy = torch.rand(n, 2, generator=g) * torch.tensor([w * 1.2, h * 1.2]) - wh / 3
    # avoid exact .5 corners, where float32 and Python rounding may legitimately differ
    return torch.cat([xy, wh], 1).to(torch.float32) + 0.013


def _lik(ii, feats=None, **kw):
    g = torch.Generator().manual_seed(3)
    feats = feats if feats is not None else HaarBoxFeatures.random(12, g)
    alpha = torch.randn(len(feats), generator=g)
    return HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, alpha, 0.25, **kw)


def test_features_match_direct_pixel_sums():
    img, ii = _frame()
    lik = _lik(ii, chunk=5)
    boxes = _boxes(23, *img.shape)
    got = lik.features_of(boxes).double()
    assert got.shape == (23, 12)
    for j in range(boxes.shape[0]):
        ref = _reference(img, lik.features, boxes[j].double().tolist())
        torch.testing.assert_close(got[j], ref, atol=2e-4, rtol=1e-5)
        want = F.logsigmoid(ref @ lik.alpha.double() + lik.bias)
        got_ll = lik.log_likelihood_of_boxes(boxes[j : j + 1]).double()[0]
        torch.testing.assert_close(got_ll, want, atol=2e-4, rtol=1e-5)


def test_uneven_banks_and_chunking_agree():
    _, ii = _frame()
    g = torch.Generator().manual_seed(5)
    split = torch.sort(torch.rand(5, 3, generator=g), 1).values
    span = torch.sort(torch.rand(5, 2, generator=g), 1).values
    boxes = _boxes(40, 37, 53)
    for nh in (0, 2, 5):  # only vertical, mixed, only horizontal
        feats = HaarBoxFeatures(split, span, nh)
        a = _lik(ii, feats, chunk=3).features_of(boxes)
        b = _lik(ii, feats).features_of(boxes)
        assert torch.equal(a, b)
        ll = _lik(ii, feats, chunk=7).log_likelihood_of_boxes(boxes)
        torch.testing.assert_close(ll, F.logsigmoid(b @ _lik(ii, feats).alpha + 0.25))


def test_call_on_states_and_in_sir_step():
    _, ii = _frame()
    lik = _lik(ii)
    motion = KleinAR()
    g = torch.Generator().manual_seed(0)
    x = motion.init(torch.tensor([[10.0, 8.0, 20.0, 16.0]]).repeat(3, 1), 50, g).double()
    out = lik(x)
    assert out.shape == (3, 50) and out.dtype == torch.float64 and bool((out <= 0).all())
    boxes = motion.to_boxes(x).reshape(-1, 4)
    torch.testing.assert_close(out.reshape(-1), lik.log_likelihood_of_boxes(boxes).double())
    r = sir_step(x, uniform_log_weights(x), motion, lik, generator=g)
    assert r.states.shape == x.shape and bool(torch.isfinite(r.log_weights).all())


def test_set_frame_changes_the_table():
    img, ii = _frame()
    lik = _lik(ii)
    boxes = _boxes(4, *img.shape)
    before = lik.features_of(boxes)
    _, ii2 = _frame(seed=9)
    lik.set_frame(ii2)
    assert not torch.equal(before, lik.features_of(boxes))
    assert torch.equal(_lik(ii2).features_of(boxes), lik.features_of(boxes))


def test_compiled_path_matches_eager_or_falls_back():
    """Where torch.compile works, the fused kernel gives the eager values (float rounding);
    where it does not, the likelihood warns and stays eager. Compiling takes seconds."""
    _, ii = _frame()
    boxes = _boxes(300, 37, 53)
    eager = _lik(ii).log_likelihood_of_boxes(boxes)
    lik = _lik(ii, compile=True)
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = lik.log_likelihood_of_boxes(boxes)
    fell_back = any("eager path" in str(w.message) for w in caught)
    assert lik.compile is not fell_back  # which path ran is known: compiled, or said it was not
    torch.testing.assert_close(got, eager, atol=1e-5, rtol=1e-5)


def test_compile_failure_falls_back_with_a_warning(monkeypatch):
    def broken():
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(hb, "_compiled", broken)
    _, ii = _frame()
    boxes = _boxes(10, 37, 53)
    lik = _lik(ii, compile=True)
    with pytest.warns(RuntimeWarning, match="eager path"):
        got = lik.log_likelihood_of_boxes(boxes)
    assert lik.compile is False
    assert torch.equal(got, _lik(ii).log_likelihood_of_boxes(boxes))


def test_bad_input_raises_typed_errors():
    _, ii = _frame()
    feats = HaarBoxFeatures.random(4)
    with pytest.raises(ShapeError, match="alpha"):
        HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.ones(3))
    with pytest.raises(ConfigError, match="sorted"):
        HaarBoxFeatures(torch.tensor([[0.5, 0.2, 0.9]]), torch.tensor([[0.1, 0.2]]), 1)
    with pytest.raises(ShapeError, match="split"):
        HaarBoxFeatures(torch.zeros(2, 2), torch.zeros(2, 2), 1)
    with pytest.raises(ConfigError, match="n_horizontal"):
        HaarBoxFeatures(torch.zeros(2, 3), torch.zeros(2, 2), 3)
    with pytest.raises(ConfigError, match="even"):
        HaarBoxFeatures.random(5)
    with pytest.raises(ConfigError, match="chunk"):
        HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.ones(4), chunk=0)
    lik = HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.ones(4))
    with pytest.raises(ShapeError, match="states"):
        lik(torch.zeros(5, 6))
    with pytest.raises(ShapeError, match="integral image"):
        lik.set_frame(torch.zeros(3))


def test_nan_weights_bias_and_bool_alpha_are_refused():
    """A NaN weight or bias made every log-likelihood NaN, reported by the filter step as
    'likelihood returned NaN' naming neither; bool weights were 0 / 1."""
    _, ii = _frame()
    feats = HaarBoxFeatures.random(4)
    with pytest.raises(ConfigError, match="alpha must be finite"):
        HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.tensor([1.0, float("nan"), 1, 1]))
    for bad in (float("nan"), float("inf"), True, "0.5"):
        with pytest.raises(ConfigError, match="bias must be a finite number"):
            HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.ones(4), bad)
    with pytest.raises(ShapeError, match="alpha must hold real numbers"):
        HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.ones(4, dtype=torch.bool))
    with pytest.raises(ConfigError, match="chunk"):
        HaarBoxLikelihood(ii, KleinAR().to_boxes, feats, torch.ones(4), chunk=True)
