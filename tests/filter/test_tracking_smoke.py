"""Integration: each motion model inside sir_step follows a synthetic moving target."""

import functools

import pytest
import torch

from torchtrack.filter import (
    BachooMotion,
    ChateauAR,
    KleinAR,
    load_chateau_toml,
    seir_step,
    sir_step,
    uniform_log_weights,
)


def _truth(t: int) -> torch.Tensor:
    """(2, 4) boxes of two targets at frame t: one moving right, one moving down-left."""
    return torch.tensor(
        [[50.0 + 3.0 * t, 60.0, 20.0, 40.0], [200.0 - 2.0 * t, 40.0 + 2.5 * t, 30.0, 30.0]],
        dtype=torch.float64,
    )


@pytest.mark.parametrize("kind", ["klein", "chateau", "chateau_fitted", "bachoo"])
@pytest.mark.parametrize("step", [sir_step, seir_step])
def test_models_follow_moving_targets(kind, step):
    g = torch.Generator().manual_seed(0)
    if kind == "klein":
        model = KleinAR(sigma_xy=2.0, sigma_wh=0.5)
    elif kind == "chateau":
        model = ChateauAR(window=(20.0, 40.0))
    elif kind == "chateau_fitted":
        from pathlib import Path

        cfg = Path(__file__).resolve().parents[2] / "torchtrack" / "data" / "dynamics_chateau.toml"
        model = load_chateau_toml(cfg, window=(20.0, 40.0))
    else:
        model = BachooMotion(min_sigma=2.0)
    x = model.init(_truth(0), 300, g)
    lw = uniform_log_weights(x)
    hist = model.new_history(_truth(0)) if kind == "bachoo" else None
    prev = None
    for t in range(1, 25):
        centre = _truth(t)[:, :2] + _truth(t)[:, 2:] / 2

        def lik(s, centre=centre):
            c = model.to_boxes(s)
            c = c[..., :2] + c[..., 2:] / 2
            return -0.5 * ((c - centre.unsqueeze(1)) ** 2).sum(-1) / 9.0

        motion = functools.partial(model.predict, history=hist) if kind == "bachoo" else model
        kw = {"mutation_std": 1.0} if step is seir_step else {}
        r = step(x, lw, motion, lik, generator=g, **kw)
        x, lw = r.states, r.log_weights
        est = model.to_boxes(r.estimate)
        est_c = est[:, :2] + est[:, 2:] / 2
        if kind == "bachoo":
            v = est_c - prev if prev is not None else torch.zeros_like(est_c)
            hist = model.update_history(hist, v)
        prev = est_c
    assert ((est_c - centre).norm(dim=1) < 4.0).all(), (kind, est_c, centre)
    assert not r.recovered.any()
