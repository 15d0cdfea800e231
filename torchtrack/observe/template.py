"""Robust template observation model (Bachoo, Le Roux and Nicolls 2011, sec. 3.1-3.3).

A target is an image patch: the pose ``(cx, cy, w, h, r)`` (centre, size, rotation about the
centre, radians) maps a unit square onto the frame, and the patch is resampled to a fixed
``S x S`` template (paper: 31 x 31). All particles' patches are sampled at once with one
``grid_sample`` call (bilinear, batched over particles); only patches that cross the frame
border get the per-pixel inside test. :func:`gaussian_blur` with :func:`antialias_sigma`
prefilters a frame before a large box is resampled to S x S (not in the paper, see
:mod:`torchtrack.track.template`).

Likelihood (eq. 5-6): for each template pixel ``eps_i = |x_i - y_i| / d`` (candidate x, template
y, intensities in [0, 1]); ``rho_i = 1`` if ``eps_i < T`` else 0; ``gamma = mean_i rho_i``.
Paper defaults: ``d = 0.05``, ``T = 1.0`` (:class:`TemplateModel` holds ``d``; the tracker
may adapt it). ``gamma`` is averaged over the template pixels that
fall inside the frame ("the total number of pixels processed"); a patch with less than
``min_inside`` of its pixels in the frame gets ``gamma = 0`` (a region leaving the frame is
not an error).

Drift correction (sec. 3.3, Matthews et al. 2004): :func:`align_ic` refines a pose by
inverse-compositional Lucas-Kanade so that the frame, warped by it, matches a reference
template (the first one): a full 2-D affine warp of template coordinates, Gauss-Newton steps
with the Hessian of the reference computed once.

Coordinates. Frame positions are continuous pixel coordinates in the package's box convention
(pixel ``i`` covers ``[i, i + 1)``, its centre is ``i + 0.5``); the 2 x 3 matrices returned by
:func:`pose_matrices` map template *indices* ``(u, v, 1)`` to frame *indices* (``x - 0.5``),
the convention of ``cv2.warpAffine(..., flags=WARP_INVERSE_MAP)``.

Colour frames are converted to luma (ITU-R BT.601: 0.299 R + 0.587 G + 0.114 B) in [0, 1];
the paper's footage is 8-bit grey.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from torchtrack.errors import ConfigError, ShapeError, is_number
from torchtrack.features.integral import check_pixel_values

__all__ = [
    "TemplateModel",
    "affine_from_params",
    "align_ic",
    "antialias_sigma",
    "gamma",
    "gaussian_blur",
    "matrix_to_pose",
    "pose_matrices",
    "rho",
    "sample_patches",
    "to_luma",
]

_LUMA = (0.299, 0.587, 0.114)


def to_luma(frame: torch.Tensor) -> torch.Tensor:
    """``(C, H, W)`` uint8 (C = 1 or 3, RGB) or float 0..255 -> ``(H, W)`` float32 in [0, 1]."""
    if not isinstance(frame, torch.Tensor) or frame.ndim != 3 or frame.shape[0] not in (1, 3):
        shape = tuple(frame.shape) if isinstance(frame, torch.Tensor) else type(frame).__name__
        raise ShapeError(f"frame must be (C, H, W) with C = 1 or 3, got {shape}")
    if frame.dtype == torch.bool or frame.is_complex():  # bools were levels 0 / 1
        raise ShapeError(f"frame must hold integer or floating levels, got {frame.dtype}")
    # NaN levels gave a NaN luma (a NaN template), 16-bit ones a luma far above 1
    check_pixel_values(frame, "frame")
    f = frame.to(torch.float32)
    if frame.shape[0] == 1:
        g = f[0]
    else:
        g = _LUMA[0] * f[0] + _LUMA[1] * f[1] + _LUMA[2] * f[2]
    return g / 255.0


def antialias_sigma(w: float, h: float, size: int = 31) -> tuple[float, float]:
    """Gaussian prefilter std ``(sigma_x, sigma_y)`` (frame pixels) for resampling a ``w x h``
    box to ``size x size``: ``max(0, (f - 1) / 2)`` with ``f`` the downsampling factor per axis
    (the rule of ``skimage.transform.resize(anti_aliasing=True)``); 0 when upsampling."""
    return max(0.0, (w / size - 1.0) / 2.0), max(0.0, (h / size - 1.0) / 2.0)


def _kernel(sigma: float, device) -> torch.Tensor:
    r = max(1, math.ceil(3.0 * sigma))
    x = torch.arange(-r, r + 1, dtype=torch.float32, device=device)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum()


def gaussian_blur(image: torch.Tensor, sigma_x: float, sigma_y: float) -> torch.Tensor:
    """Separable Gaussian blur of ``(H, W)`` (reflected borders) -> ``(H, W)`` float32; an
    axis with ``sigma < 0.1`` is left alone.

    Raises:
        ShapeError: ``image`` not 2-D.
        ConfigError: a sigma that is not a finite number (NaN left the axis unblurred).
    """
    if image.ndim != 2:
        raise ShapeError(f"image must be (H, W), got {tuple(image.shape)}")
    for name, v in (("sigma_x", sigma_x), ("sigma_y", sigma_y)):
        if not is_number(v) or not math.isfinite(v):
            raise ConfigError(f"gaussian_blur: {name} must be a finite number, got {v!r}")
    out = image.to(torch.float32)[None, None]
    if sigma_x >= 0.1:
        k = _kernel(sigma_x, image.device)
        r = (k.numel() - 1) // 2
        pad = F.pad(out, (r, r, 0, 0), mode="reflect" if r < out.shape[-1] else "replicate")
        out = F.conv2d(pad, k.reshape(1, 1, 1, -1))
    if sigma_y >= 0.1:
        k = _kernel(sigma_y, image.device)
        r = (k.numel() - 1) // 2
        pad = F.pad(out, (0, 0, r, r), mode="reflect" if r < out.shape[-2] else "replicate")
        out = F.conv2d(pad, k.reshape(1, 1, -1, 1))
    return out[0, 0]


def pose_matrices(poses: torch.Tensor, size: int = 31) -> torch.Tensor:
    """Affine maps from template indices to frame indices.

    Args:
        poses: ``(..., 5)`` ``cx, cy, w, h, r``: centre (frame pixels), box size and rotation
            (radians; the patch's axes are rotated by ``[[cos r, -sin r], [sin r, cos r]]`` in
            the image's x-right / y-down axes, i.e. clockwise on screen for r > 0).
        size: template side S.

    Returns:
        ``(..., 2, 3)`` float64 ``A`` with ``(x_idx, y_idx) = A @ (u, v, 1)`` for template index
        ``u, v`` in ``0..S-1``. Template pixel ``u`` samples the point at fraction
        ``(u + 0.5) / S`` across the box.
    """
    p = poses.to(torch.float64)
    cx, cy, w, h, r = p.unbind(-1)
    c, s = torch.cos(r), torch.sin(r)
    sx, sy = w / size, h / size
    # local = ((u + 0.5) / S - 0.5) * w = sx * u + sx * (0.5 - S / 2)
    off = 0.5 - size / 2.0
    a11, a12 = c * sx, -s * sy
    a21, a22 = s * sx, c * sy
    tx = cx - 0.5 + a11 * off + a12 * off
    ty = cy - 0.5 + a21 * off + a22 * off
    row1 = torch.stack([a11, a12, tx], -1)
    row2 = torch.stack([a21, a22, ty], -1)
    return torch.stack([row1, row2], -2)


def sample_patches(
    image: torch.Tensor, matrices: torch.Tensor, size: int = 31
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear patches of ``image`` under affine maps, all at once.

    Args:
        image: ``(H, W)`` float image.
        matrices: ``(N, 2, 3)`` template-index -> frame-index maps (:func:`pose_matrices`).
        size: template side S.

    Returns:
        ``patches (N, S, S)`` float32 (zero outside the frame) and ``inside (N, S, S)`` bool,
        True where the sample point lies within the frame (pixel centres ``0..W-1``,
        ``0..H-1``, half a pixel of slack).
    """
    if image.ndim != 2:
        raise ShapeError(f"image must be (H, W), got {tuple(image.shape)}")
    if matrices.ndim != 3 or matrices.shape[1:] != (2, 3):
        raise ShapeError(f"matrices must be (N, 2, 3), got {tuple(matrices.shape)}")
    h, w = image.shape
    n = matrices.shape[0]
    dev = image.device
    # The maps in grid_sample's normalised coordinates (align_corners=True: -1 and 1 are the
    # centres of the first and last pixels), composed in float64 on the (N, 2, 3) matrices; the
    # per-pixel work is then two broadcast multiply-adds in float32 (x = a u + b v + c).
    fx, fy = 2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)
    m = matrices.to(device=dev, dtype=torch.float64)
    scale = torch.tensor([[fx], [fy]], dtype=torch.float64, device=dev)
    mn = m * scale
    mn[:, :, 2] -= 1.0
    mn = mn.to(torch.float32)
    idx = torch.arange(size, dtype=torch.float32, device=dev)
    grid = torch.empty(n, size, size, 2, dtype=torch.float32, device=dev)
    for k in range(2):  # columns are u (x in the template), rows are v
        a, b, c = mn[:, k, 0, None, None], mn[:, k, 1, None, None], mn[:, k, 2, None, None]
        torch.add(a * idx.reshape(1, 1, size), b * idx.reshape(1, size, 1) + c, out=grid[..., k])
    img = image.to(torch.float32).reshape(1, 1, h, w)
    # One input image, the N patches stacked along the grid's rows (no per-patch image copy).
    out = F.grid_sample(
        img, grid.reshape(1, n * size, size, 2), "bilinear", "border", align_corners=True
    ).reshape(n, size, size)
    # Inside the frame: pixel centres 0..W-1 with half a pixel of slack, i.e. |g| <= 1 + f/2.
    # A patch whose four corners are inside is inside everywhere (the map is affine), so the
    # per-pixel test runs only on patches that cross the border.
    lim = torch.tensor([1.0 + fx / 2, 1.0 + fy / 2], dtype=torch.float32, device=dev)
    corners = grid[:, [0, 0, -1, -1], [0, -1, 0, -1]]  # (N, 4, 2)
    partial = ~(corners.abs() <= lim).all(2).all(1)
    inside = torch.ones(n, size, size, dtype=torch.bool, device=dev)
    if bool(partial.any()):
        sel = partial.nonzero().squeeze(1)
        ins = (grid[sel].abs() <= lim).all(-1)
        inside[sel] = ins
        out[sel] = out[sel] * ins
    return out, inside


def rho(candidates: torch.Tensor, template: torch.Tensor, d: float = 0.05, t: float = 1.0):
    """Eq. (5): ``(..., S, S)`` candidates and ``(S, S)`` template -> ``(..., S, S)`` float
    1.0 where ``|x - y| / d < T``, else 0.0."""
    return ((candidates - template).abs() / d < t).to(torch.float32)


def gamma(
    candidates: torch.Tensor,
    template: torch.Tensor,
    inside: torch.Tensor | None = None,
    d: float = 0.05,
    t: float = 1.0,
    min_inside: float = 0.5,
) -> torch.Tensor:
    """Eq. (6): ``gamma`` of ``candidates (N, S, S)`` against ``template (S, S)`` -> ``(N,)``.

    With ``inside (N, S, S)``, the mean is over the pixels inside the frame, and a patch with
    fewer than ``min_inside`` of its pixels inside gets 0.
    """
    r = rho(candidates, template, d, t)
    if inside is None:
        return r.flatten(1).mean(1)
    m = inside.flatten(1).to(torch.float32)
    cnt = m.sum(1)
    g = (r.flatten(1) * m).sum(1) / cnt.clamp_min(1.0)
    return torch.where(cnt >= min_inside * m.shape[1], g, torch.zeros_like(g))


def affine_from_params(p: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` affine parameters ``p1..p6`` -> ``(..., 3, 3)`` homogeneous matrices of
    ``W(x; p) = [[1 + p1, p3, p5], [p2, 1 + p4, p6]] x`` (Baker-Matthews ordering)."""
    one = torch.ones_like(p[..., 0])
    zero = torch.zeros_like(p[..., 0])
    rows = [
        torch.stack([1 + p[..., 0], p[..., 2], p[..., 4]], -1),
        torch.stack([p[..., 1], 1 + p[..., 3], p[..., 5]], -1),
        torch.stack([zero, zero, one], -1),
    ]
    return torch.stack(rows, -2)


def _gradients(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Central differences (one-sided at the border) of ``(S, S)`` -> ``(gx, gy)``."""
    gx = torch.empty_like(t)
    gy = torch.empty_like(t)
    gx[:, 1:-1] = (t[:, 2:] - t[:, :-2]) / 2
    gx[:, 0] = t[:, 1] - t[:, 0]
    gx[:, -1] = t[:, -1] - t[:, -2]
    gy[1:-1] = (t[2:] - t[:-2]) / 2
    gy[0] = t[1] - t[0]
    gy[-1] = t[-1] - t[-2]
    return gx, gy


def align_ic(
    image: torch.Tensor,
    reference: torch.Tensor,
    matrix: torch.Tensor,
    iterations: int = 10,
    tol: float = 1e-4,
) -> torch.Tensor:
    """Inverse-compositional Lucas-Kanade (Baker and Matthews 2004) with an affine warp.

    Finds ``p`` such that ``image`` sampled at ``matrix @ W(x; p)`` matches ``reference``
    (least squares over the template pixels inside the frame) by Gauss-Newton steps
    ``dp = H^-1 sum SD^T (I(W(x; p)) - T(x))`` and the update ``W <- W o W(dp)^-1``; the steepest
    descent images ``SD = grad T dW/dp`` and the Hessian ``H`` come from the reference alone and
    are computed once. Template coordinates are centred on the patch for conditioning.

    Args:
        image: ``(H, W)`` float image (the current frame, luma in [0, 1]).
        reference: ``(S, S)`` the template to align to (the first template for drift
            correction).
        matrix: ``(2, 3)`` starting template-index -> frame-index map.
        iterations: at most this many Gauss-Newton steps.
        tol: stop when the step moves no template corner by more than this many template pixels.

    Returns:
        ``(2, 3)`` float64 refined map.
    """
    if reference.ndim != 2 or reference.shape[0] != reference.shape[1]:
        raise ShapeError(f"reference must be (S, S), got {tuple(reference.shape)}")
    if matrix.shape != (2, 3):
        raise ShapeError(f"matrix must be (2, 3), got {tuple(matrix.shape)}")
    s = reference.shape[0]
    c = (s - 1) / 2.0
    t = reference.to(torch.float64)
    gx, gy = _gradients(t)
    dev = reference.device
    idx = torch.arange(s, dtype=torch.float64, device=dev) - c
    yy, xx = torch.meshgrid(idx, idx, indexing="ij")
    # dW/dp at p = 0 for W = [[1+p1, p3, p5], [p2, 1+p4, p6]] in centred coordinates.
    sd = torch.stack([gx * xx, gy * xx, gx * yy, gy * yy, gx, gy], -1).reshape(-1, 6)
    # Centred template coordinates: frame = M @ C @ W(x_c), with C shifting x_c back by +c.
    shift = torch.tensor(
        [[1.0, 0.0, c], [0.0, 1.0, c], [0.0, 0.0, 1.0]], dtype=torch.float64, device=dev
    )
    shift_inv = torch.tensor(
        [[1.0, 0.0, -c], [0.0, 1.0, -c], [0.0, 0.0, 1.0]], dtype=torch.float64, device=dev
    )
    m3 = torch.cat(
        [matrix.to(torch.float64), torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64, device=dev)]
    )
    warp = torch.eye(3, dtype=torch.float64, device=dev)
    corners = torch.tensor(
        [[-c, -c, 1.0], [c, -c, 1.0], [-c, c, 1.0], [c, c, 1.0]], dtype=torch.float64, device=dev
    )
    eye6 = 1e-9 * torch.eye(6, dtype=torch.float64, device=dev)
    full_hess = sd.T @ sd + eye6  # the Hessian when every template pixel is inside the frame
    n_px = s * s
    for _ in range(max(int(iterations), 0)):
        cur = m3 @ shift @ warp @ shift_inv
        patch, inside = sample_patches(image, cur[None, :2], s)
        err = (patch[0].to(torch.float64) - t).reshape(-1)
        n_in = int(inside.sum())
        if n_in < 6:
            break
        if n_in == n_px:
            hess, rhs = full_hess, sd.T @ err
        else:
            mask = inside[0].reshape(-1, 1).to(torch.float64)
            sdm = sd * mask
            hess, rhs = sdm.T @ sdm + eye6, sdm.T @ err
        try:
            dp = torch.linalg.solve(hess, rhs)
        except RuntimeError:  # singular (flat reference): nothing to align
            break
        if not bool(torch.isfinite(dp).all()):
            break
        step = affine_from_params(dp)
        warp = warp @ torch.linalg.inv(step)
        moved = (step @ corners.T - corners.T)[:2].abs().max()
        if float(moved) < tol:
            break
    out = m3 @ shift @ warp @ shift_inv
    return out[:2]


class TemplateModel:
    """The template likelihood of one target: the current template, the first one, and the
    parameters of eq. (5)-(6).

    Args:
        size: template side S (paper: 31).
        d: normalising factor of eq. (5) (paper: 0.05, for intensities in [0, 1]).
        t: threshold T of eq. (5) (paper: 1.0).
        min_inside: smallest fraction of a patch inside the frame for it to be scored.

    Example::

        model = TemplateModel()
        model.init(frame, pose)              # pose (5,) cx, cy, w, h, r
        g = model.gammas(luma, poses)        # poses (N, 5) -> (N,)
    """

    def __init__(self, size: int = 31, d: float = 0.05, t: float = 1.0, min_inside: float = 0.5):
        if int(size) < 3:
            raise ConfigError(f"template size must be >= 3 pixels, got {size}")
        if not d > 0 or not t > 0:
            raise ConfigError(f"d and T must be > 0, got d={d}, T={t}")
        if not 0.0 < min_inside <= 1.0:
            raise ConfigError(f"min_inside must be in (0, 1], got {min_inside}")
        self.size = int(size)
        self.d = float(d)
        self.t = float(t)
        self.min_inside = float(min_inside)
        self.first: torch.Tensor | None = None
        self.current: torch.Tensor | None = None

    def patches(self, luma: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``luma (H, W)``, ``poses (N, 5)`` -> ``patches (N, S, S)``, ``inside (N, S, S)``."""
        return sample_patches(luma, pose_matrices(poses, self.size), self.size)

    def init(self, luma: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
        """Store the first template, sampled at ``pose (5,)``; returns it ``(S, S)``."""
        p, _ = self.patches(luma, pose.reshape(1, 5))
        self.first = p[0].clone()
        self.current = p[0].clone()
        return self.current

    def gammas(
        self, luma: torch.Tensor, poses: torch.Tensor, template: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Eq. (6) for every pose ``(N, 5)`` against ``template`` (default: the current one)."""
        tpl = self.current if template is None else template
        p, inside = self.patches(luma, poses)
        return gamma(p, tpl, inside, self.d, self.t, self.min_inside)

    def gamma_of_matrix(
        self, luma: torch.Tensor, matrix: torch.Tensor, template: torch.Tensor
    ) -> tuple[float, torch.Tensor]:
        """``gamma`` of the patch under ``matrix (2, 3)`` and the patch ``(S, S)`` itself."""
        p, inside = sample_patches(luma, matrix[None], self.size)
        g = gamma(p, template, inside, self.d, self.t, self.min_inside)
        return float(g[0]), p[0]


def matrix_to_pose(matrix: torch.Tensor, size: int = 31) -> torch.Tensor:
    """Inverse of :func:`pose_matrices` for similarity-like maps: ``(2, 3)`` -> ``(5,)``
    ``cx, cy, w, h, r`` (an affine map's shear is dropped: w and h are the column norms, r the
    angle of the first column)."""
    m = matrix.to(torch.float64)
    a11, a21 = m[0, 0], m[1, 0]
    a12, a22 = m[0, 1], m[1, 1]
    w = torch.hypot(a11, a21) * size
    h = torch.hypot(a12, a22) * size
    r = torch.atan2(a21, a11)
    mid = (size - 1) / 2.0
    cx = a11 * mid + a12 * mid + m[0, 2] + 0.5
    cy = a21 * mid + a22 * mid + m[1, 2] + 0.5
    return torch.stack([cx, cy, w, h, r])
