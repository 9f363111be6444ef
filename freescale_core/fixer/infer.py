"""Batched inference with a trained fixer (CPU, no autograd).

:func:`fix_views` takes the same arrays a :class:`~freescale_core.fixer.data.FixerSample`
holds, for N views of one size, and returns the corrected images and the confidence maps.
"""

from __future__ import annotations

import numpy as np
import torch

from freescale_core.fixer.data import FixerSample, model_input
from freescale_core.fixer.model import FixerNet

__all__ = ["fix_views", "fix_samples", "fix_tensor"]


def fix_tensor(model: FixerNet, x: torch.Tensor, batch_size: int = 8
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """``x [N, 4+4k, H, W]`` float32 -> ``(fixed [N, 3, H, W], conf [N, 1, H, W])``."""
    was = model.training
    model.eval()
    outs_f, outs_c = [], []
    with torch.inference_mode():
        for i in range(0, len(x), batch_size):
            f, c = model(x[i:i + batch_size])
            outs_f.append(f)
            outs_c.append(c)
    model.train(was)
    return torch.cat(outs_f), torch.cat(outs_c)


def fix_views(model: FixerNet, render: np.ndarray, alpha: np.ndarray, warps: np.ndarray,
              warp_weight: np.ndarray, batch_size: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Fix N views of one size.

    Args:
        render: ``[N, H, W, 3]`` in [0, 1]; alpha ``[N, H, W]``;
        warps: ``[N, K', H, W, 3]`` (K' may differ from the model's k: padded / cut);
        warp_weight: ``[N, K', H, W]``.
    Returns:
        ``(fixed [N, H, W, 3] float32 in [0, 1], conf [N, H, W] float32 in (0, 1))``.
    """
    N = len(render)
    if N == 0:
        H, W = (render.shape[1:3] if np.ndim(render) == 4 else (0, 0))
        return np.zeros((0, H, W, 3), np.float32), np.zeros((0, H, W), np.float32)
    k = model.cfg.k
    x = torch.from_numpy(np.stack([model_input(render[i], alpha[i], warps[i], warp_weight[i], k)
                                   for i in range(N)]))
    f, c = fix_tensor(model, x, batch_size)
    return (np.ascontiguousarray(f.permute(0, 2, 3, 1).numpy()),
            np.ascontiguousarray(c[:, 0].numpy()))


def fix_samples(model: FixerNet, samples: list[FixerSample]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(fixed [H, W, 3], conf [H, W])`` per sample (any sizes; one view at a time)."""
    out = []
    for s in samples:
        f, c = fix_views(model, s.render[None], s.alpha[None], s.warps[None],
                         s.warp_weight[None], batch_size=1)
        out.append((f[0], c[0]))
    return out
