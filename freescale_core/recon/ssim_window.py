"""SSIM constants and window shared by the torch SSIM (:mod:`freescale_core.recon.losses`) and
the fused numba SSIM (:mod:`freescale_core.recon.fused_ssim`): 11x11 Gaussian window, sigma 1.5,
C1 = 0.01^2, C2 = 0.03^2 (data range 1)."""

from __future__ import annotations

import torch

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA,
                    dtype=torch.float32) -> torch.Tensor:
    """Normalised 1D Gaussian taps ``[size]``."""
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    w = torch.exp(-(x**2) / (2.0 * sigma**2))
    return (w / w.sum()).to(dtype)
