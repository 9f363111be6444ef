"""CUDA backend: dispatch to ``gsplat.rasterization`` (selected at run time)."""

from __future__ import annotations

import numpy as np
import torch

from . import _common as c


def rasterize_gsplat(means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
                     fx, fy, cx, cy, width, height, sh_degree=None, background=(0.0, 0.0, 0.0)):
    """Render with gsplat (CUDA). Same arguments and output as :func:`rasterize`.

    gsplat uses the same EWA model (+0.3 px low-pass, 3-sigma/alpha extent, 0.99 clamp,
    1/255 skip, T < 1e-4 stop); its extent rule and float ordering differ in detail, so
    outputs agree with the CPU backend to rendering precision, not bit for bit.
    """
    import gsplat  # imported lazily: absent on CPU-only machines

    from . import RenderOutput

    _, deg = c.check_inputs(means, log_scales, quats_wxyz, opacity_logits, sh, sh_degree)
    dev = means.device
    R_cw, t_cw, _ = c.camera_from_pose(world_from_cam)
    viewmat = np.eye(4)
    viewmat[:3, :3], viewmat[:3, 3] = R_cw, t_cw
    viewmats = torch.as_tensor(viewmat, dtype=torch.float32, device=dev)[None]
    Ks = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
                      dtype=torch.float32, device=dev)[None]
    bg = torch.tensor(c.background_tuple(background), dtype=torch.float32, device=dev)[None]
    k = (deg + 1) ** 2
    colors, alphas, _ = gsplat.rasterization(
        means.float(), torch.nn.functional.normalize(quats_wxyz.float(), dim=-1),
        torch.exp(log_scales.float()), torch.sigmoid(opacity_logits.float()),
        sh[:, :k].float(), viewmats, Ks, int(width), int(height), near_plane=c.NEAR,
        sh_degree=deg, backgrounds=bg, render_mode="RGB+ED", eps2d=c.LOWPASS,
        tile_size=c.TILE, packed=False)
    rgb = colors[0, ..., :3]
    depth = colors[0, ..., 3]
    alpha = alphas[0, ..., 0]
    depth = torch.where(alpha >= c.ALPHA_DEPTH_MIN, depth, torch.zeros_like(depth))
    return RenderOutput(rgb, depth, alpha)
