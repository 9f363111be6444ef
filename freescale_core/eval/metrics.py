"""Image metrics for scoring against truth."""

from __future__ import annotations

import numpy as np


# defined in the scene layer (its users include scene/ and freeviews/); re-exported here
from freescale_core.scene.images import psnr_u8  # noqa: F401


def ssim_u8(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM (11x11 Gaussian window, :func:`freescale_core.recon.losses.ssim`) of uint8
    ``[H, W, 3]`` images; NaN when a side is below the window."""
    import torch

    from freescale_core.recon.losses import SSIM_WINDOW, ssim

    if min(a.shape[:2]) < SSIM_WINDOW:
        return float("nan")
    x = torch.from_numpy(a.astype(np.float32) / 255.0)
    y = torch.from_numpy(b.astype(np.float32) / 255.0)
    return float(ssim(x, y))
