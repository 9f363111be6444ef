"""Constants and input handling shared by every rasterizer backend.

The image-formation model is standard 3DGS (EWA splatting, Kerbl et al. 2023), used by
METHOD.md stage 1 (reconstruct) and stage 7 (render). Every backend implements exactly the
rules below; ``docs/RASTERIZER.md`` explains each one.
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import ShapeError

NEAR = 0.01  # Gaussians with camera z <= NEAR are culled
LOWPASS = 0.3  # px^2 added to the diagonal of every 2D covariance (3DGS low-pass dilation)
EXTENT_SIGMA = 3.0  # a Gaussian touches only pixels within its 3-sigma ellipse
POWER_MAX = 0.5 * EXTENT_SIGMA**2  # 0.5 * d^T Sigma^-1 d <= POWER_MAX  <=>  within 3 sigma
ALPHA_MIN = 1.0 / 255.0  # contributions with alpha < ALPHA_MIN are skipped
ALPHA_MAX = 0.99  # alpha is clamped to ALPHA_MAX
T_MIN = 1e-4  # a pixel stops before the Gaussian that would bring T below T_MIN
ALPHA_DEPTH_MIN = 1e-6  # depth is 0 where accumulated alpha < ALPHA_DEPTH_MIN
FOV_CLAMP = 0.3  # Jacobian uses x/z clamped to the image +- 0.3 * tan(fov/2) (as gsplat)
TILE = 16  # tile size in pixels

# real spherical harmonics up to degree 3 (3DGS / gsplat constants)
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def check_inputs(means, log_scales, quats_wxyz, opacity_logits, sh, sh_degree):
    """Validate shapes; return ``(n, sh_degree)`` with the degree resolved.

    Args:
        means: ``[N, 3]``; log_scales: ``[N, 3]``; quats_wxyz: ``[N, 4]``;
        opacity_logits: ``[N]``; sh: ``[N, K, 3]`` with K = (deg + 1)^2 >= (sh_degree + 1)^2.
    """
    n = means.shape[0]
    for name, a, shape in (("means", means, (n, 3)), ("log_scales", log_scales, (n, 3)),
                           ("quats_wxyz", quats_wxyz, (n, 4)), ("opacity_logits",
                                                                opacity_logits, (n,))):
        if tuple(a.shape) != shape:
            raise ShapeError(name, tuple(a.shape), str(list(shape)))
    if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
        raise ShapeError("sh", tuple(sh.shape), "[N, K, 3]")
    k = sh.shape[1]
    full = int(round(np.sqrt(k))) - 1
    if (full + 1) ** 2 != k or full > 3:
        raise ShapeError("sh", tuple(sh.shape), "[N, (deg+1)^2, 3] with deg <= 3")
    if sh_degree is None:
        sh_degree = full
    if not 0 <= sh_degree <= full:
        raise ValueError(f"sh_degree={sh_degree} but sh has only degree {full} ({k} coefficients)")
    return n, int(sh_degree)


def camera_from_pose(world_from_cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split ``world_from_cam [4, 4]`` (np or torch, OpenCV axes) into camera-frame parts.

    Returns:
        ``(R_cw [3, 3], t_cw [3], centre [3])`` with ``p_cam = R_cw @ p_world + t_cw``;
        float64 numpy (no gradient w.r.t. the camera).
    """
    if isinstance(world_from_cam, torch.Tensor):
        world_from_cam = world_from_cam.detach().cpu().double().numpy()
    T = np.asarray(world_from_cam, dtype=np.float64)
    if T.shape != (4, 4):
        raise ShapeError("world_from_cam", T.shape, "[4, 4]")
    R_wc = T[:3, :3]
    centre = T[:3, 3].copy()
    R_cw = R_wc.T.copy()
    return R_cw, -R_cw @ centre, centre


def background_tuple(background) -> tuple[float, float, float]:
    if isinstance(background, torch.Tensor):
        background = background.detach().cpu().tolist()
    bg = tuple(float(v) for v in np.broadcast_to(np.asarray(background, np.float64), (3,)))
    return bg
