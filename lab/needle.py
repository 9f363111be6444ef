"""The needle regulariser tried in stop 33 (lab/results/2026-12-03_stop33/recon.md) and left
off in every preset; kept here as a measurement tool, no longer a trainer option.
A training arm with it would add ``weight * needle_loss(params["log_scales"], ratio)`` to the
loss, e.g. through ``train(..., strategy=...)``'s ``step_pre_backward`` hook."""

from __future__ import annotations

import math

import torch


def needle_loss(log_scales: torch.Tensor, max_ratio: float) -> torch.Tensor:
    """Mean over Gaussians of ``max(0, log(s_max / s_mid) - log(max_ratio))``, ``s_mid`` the
    middle axis: zero for discs and blobs, growing with the log of the excess for needles
    (one axis far longer than the other two), which show as streaks in views away from the
    training ones. A scale-ratio regulariser as in PhysGaussian (Xie et al. 2024), which
    bounds longest / shortest; here a flat disc, the shape a surface wants, is left free.
    Log-scales keep the gradient bounded. ``log_scales [N, 3]``."""
    if log_scales.shape[0] == 0:
        return log_scales.sum()
    top2 = torch.topk(log_scales, 2, dim=1).values
    return torch.relu(top2[:, 0] - top2[:, 1] - math.log(max_ratio)).mean()
