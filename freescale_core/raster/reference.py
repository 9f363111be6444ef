"""The slow, obvious rasterizer: dense pure-torch autograd, the oracle for every backend.

Every Gaussian is evaluated at every pixel (``[N, H*W]`` tensors), so this is only usable for
small images and a few hundred Gaussians. It implements the same rules as the fast backends
(see ``_common.py`` and ``docs/RASTERIZER.md``); its gradients come from torch autograd.
METHOD.md stage 1 (reconstruct) and stage 7 (render) use this image-formation model.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from . import _common as c


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities (all ``[N, ...]``, dtype of the inputs).

    Attributes:
        mean2d: ``[N, 2]`` pixel coordinates (u, v); pixel (x, y) has centre (x+.5, y+.5).
        cov2d: ``[N, 2, 2]`` 2D covariance incl. the +0.3 px^2 low-pass.
        conic: ``[N, 3]`` (a, b, c) of the inverse 2D covariance [[a, b], [b, c]].
        depth: ``[N]`` camera z.
        color: ``[N, 3]`` SH colour + 0.5, clamped at 0.
        color_raw: ``[N, 3]`` the same before the clamp.
        opacity: ``[N]`` sigmoid(opacity_logits).
        valid: ``[N]`` bool, False for culled Gaussians (z <= near, degenerate covariance).
    """

    mean2d: torch.Tensor
    cov2d: torch.Tensor
    conic: torch.Tensor
    depth: torch.Tensor
    color: torch.Tensor
    color_raw: torch.Tensor
    opacity: torch.Tensor
    valid: torch.Tensor


def quat_to_rotmat(quats_wxyz: torch.Tensor) -> torch.Tensor:
    """``[N, 4]`` (w, x, y, z), any non-zero length -> ``[N, 3, 3]`` rotation matrices."""
    q = quats_wxyz / torch.linalg.norm(quats_wxyz, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1)
    return R.reshape(q.shape[:-1] + (3, 3))


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH colour ``[N, 3]`` from coefficients ``sh [N, K, 3]`` in unit ``dirs [N, 3]``.

    Uses the first (degree + 1)^2 coefficients; 3DGS constants and basis order.
    """
    res = c.SH_C0 * sh[:, 0]
    if degree < 1:
        return res
    x, y, z = (dirs[:, i:i + 1] for i in range(3))
    res = res - c.SH_C1 * y * sh[:, 1] + c.SH_C1 * z * sh[:, 2] - c.SH_C1 * x * sh[:, 3]
    if degree < 2:
        return res
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    C2 = c.SH_C2
    res = (res + C2[0] * xy * sh[:, 4] + C2[1] * yz * sh[:, 5]
           + C2[2] * (2 * zz - xx - yy) * sh[:, 6] + C2[3] * xz * sh[:, 7]
           + C2[4] * (xx - yy) * sh[:, 8])
    if degree < 3:
        return res
    C3 = c.SH_C3
    return (res + C3[0] * y * (3 * xx - yy) * sh[:, 9] + C3[1] * xy * z * sh[:, 10]
            + C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
            + C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
            + C3[4] * x * (4 * zz - xx - yy) * sh[:, 13] + C3[5] * z * (xx - yy) * sh[:, 14]
            + C3[6] * x * (xx - 3 * yy) * sh[:, 15])


def project_reference(means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
                      fx, fy, cx, cy, width, height, sh_degree=None) -> Projected:
    """EWA projection of N Gaussians into one pinhole camera (pure torch, differentiable).

    Args:
        means: ``[N, 3]`` world centres; log_scales: ``[N, 3]``; quats_wxyz: ``[N, 4]``;
        opacity_logits: ``[N]``; sh: ``[N, K, 3]``.
        world_from_cam: ``[4, 4]`` OpenCV axes. fx, fy, cx, cy: pixels. width, height: pixels.
    Returns:
        :class:`Projected`.
    """
    _, deg = c.check_inputs(means, log_scales, quats_wxyz, opacity_logits, sh, sh_degree)
    dt, dev = means.dtype, means.device
    R_np, t_np, centre_np = c.camera_from_pose(world_from_cam)
    R_cw = torch.as_tensor(R_np, dtype=dt, device=dev)
    t_cw = torch.as_tensor(t_np, dtype=dt, device=dev)
    centre = torch.as_tensor(centre_np, dtype=dt, device=dev)

    p = means @ R_cw.T + t_cw  # [N, 3] camera frame
    x, y, z = p.unbind(-1)
    valid = z > c.NEAR
    zs = torch.where(valid, z, torch.ones_like(z))  # safe denominator for culled ones
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    # Jacobian of the pinhole projection, x/z clamped to the widened frustum (as gsplat)
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim_xp, lim_xn = (width - cx) / fx + c.FOV_CLAMP * tan_x, cx / fx + c.FOV_CLAMP * tan_x
    lim_yp, lim_yn = (height - cy) / fy + c.FOV_CLAMP * tan_y, cy / fy + c.FOV_CLAMP * tan_y
    tx = zs * torch.clamp(x / zs, -lim_xn, lim_xp)
    ty = zs * torch.clamp(y / zs, -lim_yn, lim_yp)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs**2,
                     zero, fy / zs, -fy * ty / zs**2], dim=-1).reshape(-1, 2, 3)

    Rg = quat_to_rotmat(quats_wxyz)
    M = Rg * torch.exp(log_scales)[:, None, :]  # R S
    cov3d = M @ M.transpose(1, 2)
    W = J @ R_cw  # [N, 2, 3]
    cov2d = W @ cov3d @ W.transpose(1, 2)
    cov2d = cov2d + c.LOWPASS * torch.eye(2, dtype=dt, device=dev)
    det = cov2d[:, 0, 0] * cov2d[:, 1, 1] - cov2d[:, 0, 1] * cov2d[:, 1, 0]
    valid = valid & (det > 0)
    dets = torch.where(valid, det, torch.ones_like(det))
    conic = torch.stack([cov2d[:, 1, 1] / dets, -cov2d[:, 0, 1] / dets, cov2d[:, 0, 0] / dets],
                        dim=-1)

    dirs = means - centre
    dirs = dirs / torch.linalg.norm(dirs, dim=-1, keepdim=True)
    color_raw = eval_sh(sh, dirs, deg) + 0.5
    color = torch.clamp_min(color_raw, 0.0)
    opacity = torch.sigmoid(opacity_logits)
    return Projected(mean2d, cov2d, conic, z, color, color_raw, opacity, valid)


def rasterize_reference(means, log_scales, quats_wxyz, opacity_logits, sh,
                        world_from_cam, fx, fy, cx, cy, width, height,
                        sh_degree: int | None = None, background=(0.0, 0.0, 0.0)):
    """Render one view densely; differentiable through torch autograd (the test oracle).

    Args: as :func:`freescale_core.raster.rasterize` (no ``backend``).
    Returns:
        :class:`~freescale_core.raster.RenderOutput` in the dtype of ``means``
        (float64 inputs give a float64 oracle).
    """
    width, height = int(width), int(height)
    pr = project_reference(means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
                           fx, fy, cx, cy, width, height, sh_degree)
    return blend_reference(pr, width, height, background)


def blend_reference(pr: Projected, width: int, height: int, background=(0.0, 0.0, 0.0)):
    """Dense front-to-back compositing of projected Gaussians (differentiable).

    Args:
        pr: :class:`Projected` (N Gaussians). width, height: image size in pixels.
        background: RGB behind everything.
    Returns:
        :class:`~freescale_core.raster.RenderOutput` in the dtype of ``pr.mean2d``.
    """
    from . import RenderOutput

    dt, dev = pr.mean2d.dtype, pr.mean2d.device
    bg = torch.as_tensor(c.background_tuple(background), dtype=dt, device=dev)

    # front-to-back order by camera z (stable: ties keep index order)
    order = torch.sort(pr.depth.detach(), stable=True).indices
    mean2d, conic, opac = pr.mean2d[order], pr.conic[order], pr.opacity[order]
    color, depth, valid = pr.color[order], pr.depth[order], pr.valid[order]

    ys, xs = torch.meshgrid(torch.arange(height, dtype=dt, device=dev) + 0.5,
                            torch.arange(width, dtype=dt, device=dev) + 0.5, indexing="ij")
    dx = xs.reshape(1, -1) - mean2d[:, 0:1]  # [N, P]
    dy = ys.reshape(1, -1) - mean2d[:, 1:2]
    power = 0.5 * (conic[:, 0:1] * dx * dx + conic[:, 2:3] * dy * dy) + conic[:, 1:2] * dx * dy
    raw = opac[:, None] * torch.exp(-power)
    alpha = torch.clamp_max(raw, c.ALPHA_MAX)
    keep = valid[:, None] & (power <= c.POWER_MAX) & (raw >= c.ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    # early termination: drop the Gaussian that would bring T below T_MIN and all behind it
    t_after = torch.cumprod(1.0 - alpha.detach(), dim=0)
    alpha = torch.where(t_after >= c.T_MIN, alpha, torch.zeros_like(alpha))

    one_minus = 1.0 - alpha
    t_before = torch.cat([torch.ones_like(one_minus[:1]),
                          torch.cumprod(one_minus, dim=0)[:-1]], dim=0)
    weight = alpha * t_before  # [N, P]
    t_final = torch.prod(one_minus, dim=0)  # [P]
    acc = 1.0 - t_final
    rgb = weight.T @ color + t_final[:, None] * bg
    depth_sum = weight.T @ depth
    ok = acc >= c.ALPHA_DEPTH_MIN
    depth_img = torch.where(ok, depth_sum / torch.where(ok, acc, torch.ones_like(acc)),
                            torch.zeros_like(acc))
    return RenderOutput(rgb.reshape(height, width, 3), depth_img.reshape(height, width),
                        acc.reshape(height, width))
