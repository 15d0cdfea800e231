"""Online real AdaBoost (Jin et al. Algorithm 1) against a loop reference and on a toy problem."""

import math

import pytest
import torch

from torchtrack.errors import ConfigError, NotFittedError, ShapeError
from torchtrack.learn.online_boost import OnlineRealBoost


def ref_partial_fit(st, codes, y, lam, fresh, eps, k):
    """Algorithm 1 with Python loops over selectors, candidates and samples (mini-batch order:
    every sample is scored by the histograms before the batch is added)."""
    n_sel, m = len(st["features"]), len(st["features"][0])
    p = len(y)
    lam = list(lam)
    for n in range(n_sel):
        hist = st["hist"][n]
        h = [[0.0] * m for _ in range(p)]
        for i in range(p):
            for j in range(m):
                b = codes[i][st["features"][n][j]]
                h[i][j] = 0.5 * math.log((hist[j][b][1] + eps) / (hist[j][b][0] + eps))
                if h[i][j] * y[i] >= 0:
                    st["corr"][n][j] += lam[i] * abs(h[i][j])
                else:
                    st["wrong"][n][j] += lam[i] * abs(h[i][j])
        for i in range(p):
            for j in range(m):
                hist[j][codes[i][st["features"][n][j]]][1 if y[i] > 0 else 0] += lam[i]
        e = [st["wrong"][n][j] / (st["wrong"][n][j] + st["corr"][n][j]) for j in range(m)]
        best = min(range(m), key=lambda j: (e[j], j))
        eb = e[best]
        st["selected"][n] = best
        st["alpha"][n] = math.log((1 - eb) / eb) if eb < 0.5 else 0.0
        if eb < 0.5:
            for i in range(p):
                lam[i] = lam[i] / (2 * (1 - eb)) if h[i][best] * y[i] >= 0 else lam[i] / (2 * eb)
        others = [j for j in range(m) if j != best]
        worst = max(others, key=lambda j: (e[j], -j)) if others else best
        if others:
            st["features"][n][worst] = fresh[n]
            st["hist"][n][worst] = [[0.0, 0.0] for _ in range(k)]
            st["corr"][n][worst] = 1.0
            st["wrong"][n][worst] = 1.0


def ref_decision(st, codes, eps):
    out = []
    for x in codes:
        s = 0.0
        for n, sel in enumerate(st["selected"]):
            b = x[st["features"][n][sel]]
            cell = st["hist"][n][sel][b]
            s += st["alpha"][n] * 0.5 * math.log((cell[1] + eps) / (cell[0] + eps))
        out.append(s)
    return out


@pytest.mark.parametrize("batch", [1, 5])
def test_matches_loop_reference(batch):
    n_sel, m, k, f, eps = 3, 3, 5, 4, 1e-2
    g = torch.Generator().manual_seed(0)
    codes = torch.randint(0, k, (20, f), generator=g)
    y = torch.where(codes[:, 1] >= 2, 1, -1)
    clf = OnlineRealBoost(n_sel, m, k, eps)
    gen = torch.Generator().manual_seed(7)
    st = None
    for s in range(0, 20, batch):
        c, yy = codes[s : s + batch], y[s : s + batch]
        # The generator draws the initial features, then per call the replacements.
        probe = torch.Generator().manual_seed(7)
        probe.set_state(gen.get_state())
        if st is None:
            feats = torch.randint(f, (n_sel, m), generator=probe)
            st = {
                "features": feats.tolist(),
                "hist": [[[[0.0, 0.0] for _ in range(k)] for _ in range(m)] for _ in range(n_sel)],
                "corr": [[1.0] * m for _ in range(n_sel)],
                "wrong": [[1.0] * m for _ in range(n_sel)],
                "selected": [0] * n_sel,
                "alpha": [0.0] * n_sel,
            }
        fresh = torch.randint(f, (n_sel,), generator=probe).tolist()
        clf.partial_fit(c, yy, generator=gen)
        ref_partial_fit(st, c.tolist(), yy.tolist(), [1.0] * len(yy), fresh, eps, k)
        assert clf.features_.tolist() == st["features"]
        assert clf.selected_.tolist() == st["selected"]
        torch.testing.assert_close(clf.correct_, torch.tensor(st["corr"], dtype=torch.float64))
        torch.testing.assert_close(clf.wrong_, torch.tensor(st["wrong"], dtype=torch.float64))
        torch.testing.assert_close(clf.alpha_, torch.tensor(st["alpha"], dtype=torch.float64))
        torch.testing.assert_close(clf.hist_, torch.tensor(st["hist"], dtype=torch.float64))
    torch.testing.assert_close(
        clf.decision_function(codes),
        torch.tensor(ref_decision(st, codes.tolist(), eps), dtype=torch.float64),
    )
    assert clf.n_samples_seen_ == 20


def test_error_falls_on_a_separable_pixel_problem():
    g = torch.Generator().manual_seed(1)
    clf = OnlineRealBoost(n_selectors=5, n_candidates=3, n_bins=16)
    errors = []
    for _ in range(15):
        codes = torch.randint(0, 16, (500, 8), generator=g)
        y = torch.where(codes[:, 5] < 8, 1, -1)  # feature 5 separates the labels
        if hasattr(clf, "hist_"):  # test, then train (prequential error)
            errors.append(float((clf.predict(codes) != y).float().mean()))
        clf.partial_fit(codes, y, generator=g)
    assert errors[0] > 0.2  # the random start rarely holds feature 5 everywhere
    assert errors[-1] < 0.02 and min(errors[-3:]) < errors[0]
    assert (clf.features_[torch.arange(5), clf.selected_] == 5).any()


def test_sample_weights_and_zero_one_labels():
    codes = torch.tensor([[0], [1], [1]])
    a = OnlineRealBoost(1, 1, 2).partial_fit(codes, torch.tensor([0, 1, 1]))
    b = OnlineRealBoost(1, 1, 2).partial_fit(codes, torch.tensor([-1, 1, 1]))
    torch.testing.assert_close(a.hist_, b.hist_)
    w = OnlineRealBoost(1, 1, 2).partial_fit(
        codes, torch.tensor([-1, 1, 1]), sample_weight=torch.tensor([2.0, 1.0, 0.5])
    )
    torch.testing.assert_close(w.hist_[0, 0, :, 0], torch.tensor([2.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(w.hist_[0, 0, :, 1], torch.tensor([0.0, 1.5], dtype=torch.float64))


def test_errors():
    clf = OnlineRealBoost(2, 2, 4)
    with pytest.raises(NotFittedError, match="not fitted"):
        clf.decision_function(torch.zeros(1, 2, dtype=torch.long))
    with pytest.raises(ShapeError, match="integer bin codes"):
        clf.partial_fit(torch.zeros(3, 2), torch.ones(3))
    with pytest.raises(ShapeError, match=r"must lie in 0\.\.3"):
        clf.partial_fit(torch.full((3, 2), 4), torch.ones(3))
    with pytest.raises(ShapeError, match="y must be"):
        clf.partial_fit(torch.zeros(3, 2, dtype=torch.long), torch.ones(2))
    with pytest.raises(ShapeError, match="labels"):
        clf.partial_fit(torch.zeros(3, 2, dtype=torch.long), torch.tensor([2, 1, 1]))
    clf.partial_fit(torch.zeros(3, 2, dtype=torch.long), torch.tensor([1, -1, 1]))
    with pytest.raises(ShapeError, match="fitted on 2"):
        clf.decision_function(torch.zeros(3, 3, dtype=torch.long))
    with pytest.raises(ConfigError, match="n_selectors"):
        OnlineRealBoost(0).partial_fit(torch.zeros(1, 1, dtype=torch.long), torch.ones(1))
    with pytest.raises(ConfigError, match="eps"):
        OnlineRealBoost(eps=0).partial_fit(torch.zeros(1, 1, dtype=torch.long), torch.ones(1))


def test_bad_sample_weights_and_eps_are_refused_before_any_update():
    """A NaN importance went into the histograms for good (every later confidence NaN), a
    negative one trained against its label; eps=True was an eps of 1 and inf made every weak
    hypothesis 0; all without a word."""
    from torchtrack.errors import DataError

    codes, y = torch.tensor([[0], [1], [1]]), torch.tensor([-1, 1, 1])
    for bad in (math.nan, -1.0, math.inf):
        clf = OnlineRealBoost(1, 1, 2)
        with pytest.raises(DataError, match="sample_weight must be finite and >= 0"):
            clf.partial_fit(codes, y, sample_weight=torch.tensor([1.0, bad, 1.0]))
        assert not hasattr(clf, "hist_")  # refused before the classifier started
    for eps in (True, math.inf):
        with pytest.raises(ConfigError, match="eps must be a finite number > 0"):
            OnlineRealBoost(1, 1, 2, eps=eps).partial_fit(codes, y)
