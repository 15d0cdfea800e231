import math

import pytest
import torch

from torchtrack.errors import ConfigError, DataError
from torchtrack.filter.dynamics_fit import (
    chateau_states,
    fit_chateau_dynamics,
    load_chateau_toml,
    save_chateau_toml,
)
from torchtrack.filter.motion import ChateauAR, default_chateau_B

WINDOW = (20.0, 40.0)


def _true_model():
    a = torch.zeros(6, 6, dtype=torch.float64)
    a[0, 0], a[0, 2] = 1.7, -0.7  # damped velocity on cx
    a[1, 1], a[1, 3] = 1.5, -0.5
    a[0, 4], a[0, 5] = 3.0, -3.0  # cx moves with the scale change (a cross term)
    a[4, 4], a[4, 5] = 1.3, -0.3
    a[2, 0], a[3, 1], a[5, 4] = 1.0, 1.0, 1.0
    sigma = torch.tensor(
        [[4.0, 1.0, 0.01], [1.0, 2.0, 0.0], [0.01, 0.0, 1e-3]], dtype=torch.float64
    )
    return a, sigma


def _simulate(n_tracks=40, t=150, seed=0):
    a, sigma = _true_model()
    m = ChateauAR(a, default_chateau_B(), sigma, window=WINDOW)
    g = torch.Generator().manual_seed(seed)
    box0 = torch.tensor([[100.0, 100.0, 20.0, 40.0]], dtype=torch.float64).repeat(n_tracks, 1)
    x = m.from_boxes(box0).unsqueeze(1)  # (n_tracks, 1, 6), s = 1
    boxes = [m.to_boxes(x[:, 0])]
    for _ in range(t - 1):
        x = m.predict(x, g)
        boxes.append(m.to_boxes(x[:, 0]))
    tr = torch.stack(boxes, 1)  # (n_tracks, T, 4)
    return [tr[i] for i in range(n_tracks)], a, sigma


def test_fit_recovers_known_A_B_Sigma():
    tracks, a, sigma = _simulate()
    fit = fit_chateau_dynamics(tracks, window=WINDOW)
    assert fit.n_transitions == 40 * 148 and fit.n_tracks == 40
    # Within 4.5 least-squares standard errors (elementwise), and the standard errors are
    # small enough for the claim to mean something.
    assert ((fit.A - a).abs() <= 4.5 * fit.A_stderr + 1e-12).all(), (fit.A - a) / fit.A_stderr
    assert fit.A_stderr[4].max() < 0.05  # the s row; s columns of the c rows are loose
    assert (fit.A_stderr[[0, 1, 4]][:, [0, 1, 2, 3]] < 0.03).all()
    torch.testing.assert_close(fit.B, default_chateau_B())
    # Sample covariance: standard error of entry (i, j) is sqrt((S_ii S_jj + S_ij^2) / M).
    d = torch.diagonal(sigma)
    se = torch.sqrt((d.unsqueeze(0) * d.unsqueeze(1) + sigma.square()) / fit.n_transitions)
    assert ((fit.Sigma - sigma).abs() <= 5 * se).all(), (fit.Sigma - sigma) / se


def test_fit_relative_to_first_box_and_nan_gaps():
    tracks, a, _ = _simulate(seed=1)
    # s relative to the first box equals s relative to WINDOW here (first box = WINDOW size)
    gapped = []
    for tr in tracks:
        tr = tr.clone()
        tr[50:53] = math.nan  # absent target: transitions touching these frames are skipped
        gapped.append(tr)
    fit = fit_chateau_dynamics(gapped)
    # 150 frames, 3 NaN: valid runs 0-49 (48 transitions) and 53-149 (95 transitions)
    assert fit.n_transitions == 40 * (48 + 95)
    assert ((fit.A - a).abs() <= 4.5 * fit.A_stderr + 1e-12).all()
    assert torch.isfinite(fit.Sigma).all()


def test_states_scale_is_geometric_mean_ratio():
    boxes = torch.tensor([[0.0, 0.0, 10.0, 20.0], [1.0, 1.0, 20.0, 40.0], [math.nan] * 4])
    st, valid = chateau_states(boxes)
    assert valid.tolist() == [False, True, False]
    torch.testing.assert_close(
        st[1], torch.tensor([11.0, 21.0, 5.0, 10.0, 2.0, 1.0], dtype=torch.float64)
    )


def test_fit_errors():
    with pytest.raises(DataError, match="at least 12 transitions"):
        fit_chateau_dynamics([torch.zeros(5, 4) + 1])
    with pytest.raises(DataError, match=r"must be \(T, 4\)"):
        fit_chateau_dynamics([torch.zeros(5, 3)])
    with pytest.raises(DataError, match="w <= 0"):
        fit_chateau_dynamics([torch.zeros(20, 4)])


def test_bad_windows_bool_tracks_and_infinite_values_are_refused():
    """A NaN window gave a fit of NaN scales (A's scale row nonsense), a negative one an rms
    of 0 on the scale, (True, True) a 1 x 1 window; bool tracks were 0 / 1 pixel boxes and an
    infinite value was taken as an absent target; all without a word."""
    tracks, _, _ = _simulate(n_tracks=3, t=20)
    for bad in ((math.nan, 1.0), (-20.0, 40.0), (True, True), 5):
        with pytest.raises(ConfigError, match=r"fit_chateau_dynamics: window must be \(w, h\)"):
            fit_chateau_dynamics(tracks, window=bad)
        with pytest.raises(ConfigError, match=r"chateau_states: window must be"):
            chateau_states(tracks[0], window=bad)
    with pytest.raises(DataError, match=r"real numbers x, y, w, h, got torch\.bool"):
        fit_chateau_dynamics([t.bool() for t in tracks])
    bad = tracks[0].clone()
    bad[5, 0] = math.inf
    with pytest.raises(DataError, match="a track has an infinite value"):
        fit_chateau_dynamics([bad, *tracks[1:]])
    with pytest.raises(ConfigError, match=r"ChateauAR: window must be \(w, h\)"):
        ChateauAR(window=(0.0, 1.0))  # the one check, shared


def test_toml_round_trip(tmp_path):
    tracks, _, _ = _simulate(n_tracks=5, t=40)
    fit = fit_chateau_dynamics(tracks, window=WINDOW)
    p = tmp_path / "dyn.toml"
    save_chateau_toml(p, fit, comment="test")
    m = load_chateau_toml(p, window=WINDOW)
    torch.testing.assert_close(m.A, fit.A)
    torch.testing.assert_close(m.Sigma, fit.Sigma)
    p.write_text("extra = 1\n" + p.read_text())
    with pytest.raises(ConfigError, match="unknown parameter keys"):
        load_chateau_toml(p)
    p.write_text("A = [[1")
    with pytest.raises(ConfigError, match="cannot read dynamics config"):
        load_chateau_toml(p)


def test_shipped_config_loads():
    from pathlib import Path

    cfg = Path(__file__).resolve().parents[2] / "torchtrack" / "data" / "dynamics_chateau.toml"
    m = load_chateau_toml(cfg)
    # Real pedestrian / face / vehicle tracks: close to constant velocity or constant position.
    row = m.A[0]
    assert abs(float(row[0] + row[2]) - 1.0) < 0.05  # translation invariance c_t, c_{t-1}
    assert torch.linalg.eigvalsh(m.Sigma).min() > 0


def _cv_tracks(n_tracks, t, accel_sd, jitter_sd, seed):
    """Constant-velocity tracks with white acceleration noise, labelled with jitter."""
    g = torch.Generator().manual_seed(seed)
    acc = accel_sd * torch.randn((n_tracks, t, 2), generator=g, dtype=torch.float64)
    vel = 2.0 + acc.cumsum(1)
    c = 100.0 + vel.cumsum(1)
    c = c + jitter_sd * torch.randn((n_tracks, t, 2), generator=g, dtype=torch.float64)
    wh = torch.tensor([20.0, 40.0], dtype=torch.float64).expand(n_tracks, t, 2)
    return [torch.cat([c[i] - wh[i] / 2, wh[i]], 1) for i in range(n_tracks)]


def test_jitter_corrected_noise_recovers_the_motion_under_label_jitter():
    # Labels jitter by 1 px; the targets accelerate by 0.5 px / frame: the plain residual
    # variance is ~0.25 + 6 * 1 = 6.25 px^2, the motion's share 0.25.
    tracks = _cv_tracks(12, 1000, accel_sd=0.5, jitter_sd=1.0, seed=0)
    # One erratic track (a shaking camera) must not set everyone's noise: the median ignores it.
    tracks += _cv_tracks(1, 1000, accel_sd=20.0, jitter_sd=1.0, seed=1)
    raw = fit_chateau_dynamics(tracks, structure="constant_velocity")
    fit = fit_chateau_dynamics(tracks, structure="constant_velocity", noise="jitter_corrected")
    assert raw.Sigma[0, 0] > 6.0
    assert 0.1 < float(fit.Sigma[0, 0]) < 0.45 and fit.Sigma[0, 0] == fit.Sigma[1, 1]
    assert fit.Sigma[0, 1] == 0 and fit.Sigma[2, 2] > 0  # diagonal, positive definite
    torch.testing.assert_close(fit.A, raw.A)
    fit.model()  # a valid ChateauAR


def test_jitter_corrected_noise_errors():
    tracks = _cv_tracks(2, 30, accel_sd=0.5, jitter_sd=1.0, seed=0)
    with pytest.raises(ConfigError, match="constant_velocity"):
        fit_chateau_dynamics(tracks, noise="jitter_corrected")
    with pytest.raises(ConfigError, match="noise must be"):
        fit_chateau_dynamics(tracks, structure="constant_velocity", noise="robust")
    with pytest.raises(DataError, match="consecutive residual pairs"):
        fit_chateau_dynamics(
            _cv_tracks(2, 15, 0.5, 1.0, 0), structure="constant_velocity", noise="jitter_corrected"
        )
