"""Template observation model (Bachoo et al. eq. 5-6, affine patch sampling, IC Lucas-Kanade)
against slow references: a NumPy loop, cv2.warpAffine, a known warp."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchtrack.errors import ConfigError, ShapeError
from torchtrack.observe.template import (
    TemplateModel,
    align_ic,
    gamma,
    matrix_to_pose,
    pose_matrices,
    rho,
    sample_patches,
    to_luma,
)


def _smooth_image(h: int = 80, w: int = 100, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(1, 1, h, w, generator=g)
    return torch.nn.functional.avg_pool2d(img, 5, 1, 2)[0, 0]


def _gamma_loop(cands: np.ndarray, tpl: np.ndarray, d: float, t: float) -> np.ndarray:
    out = np.zeros(len(cands))
    for k, c in enumerate(cands):
        total = 0.0
        for i in range(tpl.shape[0]):
            for j in range(tpl.shape[1]):
                eps = abs(float(c[i, j]) - float(tpl[i, j])) / d
                total += 1.0 if eps < t else 0.0
        out[k] = total / tpl.size
    return out


@pytest.mark.parametrize(("d", "t"), [(0.05, 1.0), (0.1, 0.5), (0.02, 2.0)])
def test_gamma_matches_numpy_loop(d, t):
    g = torch.Generator().manual_seed(1)
    tpl = torch.rand(31, 31, generator=g)
    cands = (tpl + 0.08 * torch.randn(5, 31, 31, generator=g)).clamp(0, 1)
    ours = gamma(cands, tpl, d=d, t=t).numpy()
    ref = _gamma_loop(cands.numpy(), tpl.numpy(), d, t)
    np.testing.assert_allclose(ours, ref, atol=1e-6)
    assert rho(cands, tpl, d, t).shape == (5, 31, 31)


def test_gamma_only_counts_pixels_inside():
    tpl = torch.zeros(4, 4)
    cand = torch.zeros(2, 4, 4)
    cand[:, :, 2:] = 1.0  # right half mismatches
    inside = torch.ones(2, 4, 4, dtype=torch.bool)
    inside[0, :, 2:] = False  # patch 0: the mismatching half is outside the frame
    inside[1, :, 1:] = False  # patch 1: only a quarter inside -> below min_inside
    g = gamma(cand, tpl, inside, d=0.05, t=1.0, min_inside=0.5)
    assert g.tolist() == [1.0, 0.0]


def test_luma_bt601_and_gray():
    rgb = torch.tensor([255, 0, 0], dtype=torch.uint8).view(3, 1, 1).repeat(1, 2, 2)
    assert torch.allclose(to_luma(rgb), torch.full((2, 2), 0.299))
    gray = torch.full((1, 2, 2), 51, dtype=torch.uint8)
    assert torch.allclose(to_luma(gray), torch.full((2, 2), 0.2))
    with pytest.raises(ShapeError, match="C = 1 or 3"):
        to_luma(torch.zeros(2, 4, 4))


@pytest.mark.parametrize(
    "pose",
    [
        [50.0, 40.0, 20.0, 15.0, 0.1],
        [30.5, 22.0, 41.0, 33.0, -0.4],
        [8.0, 6.0, 30.0, 30.0, 0.3],  # partly outside the frame
    ],
)
def test_sampling_equals_cv2_warp_affine(pose):
    img = _smooth_image()
    m = pose_matrices(torch.tensor([pose]))
    p, inside = sample_patches(img, m)
    ref = cv2.warpAffine(
        img.numpy(),
        m[0].numpy(),
        (31, 31),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    ins = inside[0].numpy()
    assert ins.any()
    np.testing.assert_allclose(p[0].numpy()[ins], ref[ins], atol=1e-4)
    assert (p[0].numpy()[~ins] == 0).all()


def test_pose_matrix_round_trip_and_geometry():
    pose = torch.tensor([40.0, 30.0, 20.0, 10.0, 0.25], dtype=torch.float64)
    m = pose_matrices(pose)
    assert torch.allclose(matrix_to_pose(m), pose, atol=1e-9)
    # Unrotated: template pixel 0 samples the centre of the box's first 1/31 column.
    m0 = pose_matrices(torch.tensor([40.0, 30.0, 31.0, 31.0, 0.0]))
    x_idx = m0[0, 0] * 0 + m0[0, 1] * 0 + m0[0, 2]
    assert float(x_idx) == pytest.approx(40.0 - 15.5 + 0.5 - 0.5)


def test_ic_lucas_kanade_recovers_known_warp():
    img = _smooth_image(seed=3)
    true_pose = torch.tensor([50.0, 40.0, 24.0, 20.0, 0.1], dtype=torch.float64)
    tpl, _ = sample_patches(img, pose_matrices(true_pose)[None])
    start = true_pose.clone()
    start[0] += 1.5
    start[1] -= 1.0
    start[2] *= 1.05
    start[4] += 0.05
    m = align_ic(img, tpl[0], pose_matrices(start), iterations=30)
    got = matrix_to_pose(m)
    assert torch.allclose(got[:2], true_pose[:2], atol=0.05)
    assert torch.allclose(got[2:4], true_pose[2:4], atol=0.1)
    assert float(got[4]) == pytest.approx(0.1, abs=5e-3)
    # And the start was measurably off (the test can fail).
    m_start = pose_matrices(start)
    p_start, _ = sample_patches(img, m_start[None])
    p_end, _ = sample_patches(img, m[None])
    assert float((p_end[0] - tpl[0]).abs().mean()) < 0.2 * float((p_start[0] - tpl[0]).abs().mean())


def test_template_model_and_errors():
    img = _smooth_image()
    model = TemplateModel()
    pose = torch.tensor([50.0, 40.0, 20.0, 20.0, 0.0])
    model.init(img, pose)
    g = model.gammas(img, torch.stack([pose, pose + torch.tensor([15.0, 0, 0, 0, 0])]))
    assert float(g[0]) == 1.0 and float(g[1]) < 0.8
    with pytest.raises(ConfigError, match="template size"):
        TemplateModel(size=2)
    with pytest.raises(ConfigError, match="d and T"):
        TemplateModel(d=0)
    with pytest.raises(ShapeError, match=r"\(N, 2, 3\)"):
        sample_patches(img, torch.zeros(2, 3))
    with pytest.raises(ShapeError, match=r"\(S, S\)"):
        align_ic(img, torch.zeros(3, 4), torch.zeros(2, 3))
