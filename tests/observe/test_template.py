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
    antialias_sigma,
    gamma,
    gaussian_blur,
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


@pytest.mark.parametrize(("sx", "sy"), [(1.5, 0.7), (0.0, 2.2), (0.05, 0.05), (3.0, 3.0)])
def test_gaussian_blur_equals_cv2(sx, sy):
    img = torch.rand(37, 53, generator=torch.Generator().manual_seed(2))
    ours = gaussian_blur(img, sx, sy).numpy()
    rx = max(1, int(np.ceil(3 * sx))) if sx >= 0.1 else 0
    ry = max(1, int(np.ceil(3 * sy))) if sy >= 0.1 else 0
    kx = cv2.getGaussianKernel(2 * rx + 1, sx) if rx else np.ones((1, 1))
    ky = cv2.getGaussianKernel(2 * ry + 1, sy) if ry else np.ones((1, 1))
    ref = cv2.sepFilter2D(img.numpy(), cv2.CV_64F, kx, ky, borderType=cv2.BORDER_REFLECT_101)
    np.testing.assert_allclose(ours, ref, atol=1e-5)
    if rx == ry == 0:
        assert np.array_equal(ours, img.numpy())


def test_antialias_sigma_rule():
    # skimage.transform.resize's anti-aliasing rule: (factor - 1) / 2, none when upsampling.
    assert antialias_sigma(31.0 * 3, 31.0 * 5) == (1.0, 2.0)
    assert antialias_sigma(20.0, 31.0) == (0.0, 0.0)
    with pytest.raises(ShapeError, match=r"\(H, W\)"):
        gaussian_blur(torch.zeros(1, 4, 4), 1.0, 1.0)


def test_batched_sampling_equals_one_by_one():
    # The fast path (patches wholly inside skip the per-pixel test) against single-pose calls.
    img = _smooth_image(seed=5)
    g = torch.Generator().manual_seed(0)
    n = 64
    poses = torch.stack(
        [
            torch.rand(n, generator=g) * 120 - 10,  # some centres off the 100 x 80 frame
            torch.rand(n, generator=g) * 100 - 10,
            torch.rand(n, generator=g) * 40 + 5,
            torch.rand(n, generator=g) * 40 + 5,
            torch.rand(n, generator=g) - 0.5,
        ],
        1,
    )
    p, inside = sample_patches(img, pose_matrices(poses))
    partial = (~inside.flatten(1).all(1)).sum()
    assert 0 < int(partial) < n
    # Slow reference of the inside mask: every sample point through the float64 matrix.
    m = pose_matrices(poses).numpy()
    v, u = np.meshgrid(np.arange(31.0), np.arange(31.0), indexing="ij")
    x = m[:, 0, 0, None, None] * u + m[:, 0, 1, None, None] * v + m[:, 0, 2, None, None]
    y = m[:, 1, 0, None, None] * u + m[:, 1, 1, None, None] * v + m[:, 1, 2, None, None]
    ref = (x >= -0.5) & (x <= 100 - 0.5) & (y >= -0.5) & (y <= 80 - 0.5)
    assert (ref == inside.numpy()).mean() > 0.9999
    for k in range(n):
        pk, ik = sample_patches(img, pose_matrices(poses[k : k + 1]))
        assert torch.equal(ik[0], inside[k])
        np.testing.assert_allclose(pk[0].numpy(), p[k].numpy(), atol=1e-6)


def test_luma_and_blur_refuse_what_is_no_image_or_sigma():
    """A NaN frame gave a NaN luma (a NaN template), 16-bit levels a luma far above 1, bools
    levels 0 / 1; a NaN sigma left its axis unblurred; all without a word."""
    from torchtrack.errors import DataError

    for bad in (torch.full((1, 4, 4), float("nan")), torch.full((3, 4, 4), 1000.0)):
        with pytest.raises(DataError, match="frame hold"):
            to_luma(bad)
    with pytest.raises(ShapeError, match=r"integer or floating levels, got torch\.bool"):
        to_luma(torch.ones(1, 4, 4, dtype=torch.bool))
    for bad in (float("nan"), "1", True):
        with pytest.raises(ConfigError, match="gaussian_blur: sigma_x must be a finite number"):
            gaussian_blur(torch.zeros(8, 8), bad, 0.0)
