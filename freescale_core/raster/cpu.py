"""CPU backend (placeholder: the numba kernels land next; this calls the reference)."""

from __future__ import annotations

import torch


def rasterize_cpu(means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
                  fx, fy, cx, cy, width, height, sh_degree=None, background=(0.0, 0.0, 0.0)):
    from . import RenderOutput
    from .reference import rasterize_reference

    out = rasterize_reference(means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
                              fx, fy, cx, cy, width, height, sh_degree, background)
    return RenderOutput(out.rgb.to(torch.float32), out.depth.to(torch.float32),
                        out.alpha.to(torch.float32))
