"""Fused tracker (calibrated detector x co-trained pixel likelihood): weight composition, the
raw-margin ablation's rescaling, configuration errors, a short real-data run."""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.boxes import box_iou
from torchtrack.errors import ConfigError
from torchtrack.track.fused import FusedTracker, fused_log_weights, minmax_rescale


def test_fused_log_weights_composition():
    p = torch.tensor([[0.9, 0.5, 0.0]])
    lc = torch.tensor([[-1.0, -2.0, -0.5]], dtype=torch.float64)
    out = fused_log_weights(p, lc, 2.0, 0.5, det_floor=1e-6)
    ref = [2 * math.log(0.9) - 0.5, 2 * math.log(0.5) - 1.0, 2 * math.log(1e-6) - 0.25]
    assert torch.allclose(out, torch.tensor([ref], dtype=torch.float64))
    # a = 0 drops the detector (also its zero probabilities); b = 0 the co-training term.
    assert torch.allclose(fused_log_weights(p, lc, 0.0, 1.0), lc)
    inf = torch.tensor([[-math.inf, 0.0, 0.0]], dtype=torch.float64)
    det_only = fused_log_weights(p, inf, 1.0, 0.0)
    assert torch.isfinite(det_only).all()
    # The product of the two likelihoods (a = b = 1) ranks particles by p * L.
    w = fused_log_weights(p, lc, 1.0, 1.0).exp()
    assert torch.allclose(w, p.double().clamp_min(1e-6) * lc.exp())


def test_minmax_rescale():
    x = torch.tensor([[1.0, 3.0, 2.0, -math.inf], [5.0, 5.0, 5.0, 5.0]], dtype=torch.float64)
    y = minmax_rescale(x)
    assert y.tolist() == [[0.0, 1.0, 0.5, 0.0], [1.0, 1.0, 1.0, 1.0]]


def test_config_errors():
    with pytest.raises(ConfigError, match="both 0"):
        FusedTracker(det_weight=0.0, cotrain_weight=0.0)
    with pytest.raises(ConfigError, match="calibration must be"):
        FusedTracker(calibration="isotonic")
    with pytest.raises(ConfigError, match="unknown key"):
        FusedTracker(particles=3)
    with pytest.raises(ConfigError, match=r"det_weight must be in \[0, 100\], got 1e\+308"):
        FusedTracker(det_weight=1e308)  # overflowed the weights later
    with pytest.raises(ConfigError, match=r"context \(window over box height\)"):
        FusedTracker(context=1e308)


def test_raw_margins_are_an_increasing_map_of_probabilities():
    # Platt: p = sigmoid(-(A m + B)) is monotone in the margin, so the raw and calibrated
    # detector terms rank windows alike; only the scale differs.
    tr = FusedTracker("pedestrian", n_particles=20)
    g = torch.Generator().manual_seed(0)
    frame = (torch.rand(3, 96, 64, generator=g) * 255).to(torch.uint8)
    tr.init(frame, (16.0, 16.0, 32.0, 64.0))
    wins = torch.tensor([[[0.0, 0.0, 48.0, 96.0], [8.0, 8.0, 40.0, 80.0], [4, 2, 30, 60]]])
    m = tr.margins(frame, wins)
    p = tr._probabilities(frame, wins)
    order_m = torch.argsort(m[0])
    order_p = torch.argsort(p[0])
    assert torch.equal(order_m, order_p) or torch.allclose(p[0], p[0, 0].expand(3))
    off = tr.margins(frame, torch.tensor([[[500.0, 500.0, 10.0, 10.0]]]))
    assert off[0, 0] == -math.inf


def test_real_sequence_short(data_dir):
    from torchtrack.io.sequences import load_sequence

    seq = load_sequence(data_dir / "tracking" / "otb" / "Crossing")[0]
    tr = FusedTracker("pedestrian", n_particles=50, generator=torch.Generator().manual_seed(0))
    ious = []
    for i, frame in zip(range(6), seq.open(), strict=False):
        st = tr.init(frame, seq.boxes[0]) if i == 0 else tr.update(frame)
        if i:
            ious.append(float(box_iou(st.box, seq.boxes[i : i + 1])[0]))
    assert sum(ious) / len(ious) > 0.45
    assert len(tr.history) == 5


def test_naive_calibration_is_the_papers_fixed_range_rescale():
    # Chateau et al. 2.4: m_r = (m - a_min) / (a_max - a_min), a fixed map (not per frame).
    tr = FusedTracker("pedestrian", n_particles=20, calibration="naive")
    clf = tr.detector.classifier
    lo, hi = tr.margin_range()
    # the bundled pedestrian has boosted trees: the sums of each tree's smallest / largest leaf
    assert lo == pytest.approx(float(clf.leaf_.double().min(1).values.sum()))
    assert hi == pytest.approx(float(clf.leaf_.double().max(1).values.sum()))
    g = torch.Generator().manual_seed(1)
    frame = (torch.rand(3, 96, 64, generator=g) * 255).to(torch.uint8)
    tr.init(frame, (16.0, 16.0, 32.0, 64.0))
    states = tr._states[:, :5]
    m = tr.margins(frame, tr.window_boxes(states))
    got, p = tr.detector_term(frame, states)
    torch.testing.assert_close(p, tr._probabilities(frame, tr.window_boxes(states)))
    ref = torch.where(torch.isfinite(m), (m - lo) / (hi - lo), torch.zeros_like(m))
    torch.testing.assert_close(got, ref)
    assert bool(((got >= 0) & (got <= 1)).all())


def test_naive_calibration_needs_a_bounded_margin():
    tr = FusedTracker("pedestrian", n_particles=20, calibration="naive")
    det = tr.observation.detector  # what scores the particles (the margins come from it)
    tr.observation.detector = type(det)(
        bank=det.bank,
        feature_index=det.feature_index,
        classifier=type("Unbounded", (), {"n_features_in_": det.feature_index.numel()})(),
        calibrator=det.calibrator,
    )
    with pytest.raises(ConfigError, match="bounded margin"):
        tr.margin_range()
