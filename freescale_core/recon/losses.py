"""Image losses and metrics of the reconstruction stage (METHOD.md stage 1; 3DGS loss).

SSIM uses an 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2 (data range 1) and
averages the SSIM map over the *valid* region only (no padding), which is exactly what
``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1)`` reports.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from freescale_core.recon.ssim_window import (  # re-exported: losses.SSIM_* stay valid
    SSIM_C1,
    SSIM_C2,
    SSIM_SIGMA,
    SSIM_WINDOW,
    gaussian_window,
)


def _blur(x: torch.Tensor, w1d: torch.Tensor) -> torch.Tensor:
    """Separable valid-mode Gaussian filter of ``x [B, C, H, W]`` per channel."""
    c = x.shape[1]
    k = w1d.numel()
    x = F.conv2d(x, w1d.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
    return F.conv2d(x, w1d.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)


def ssim_map(img: torch.Tensor, ref: torch.Tensor, impl: str = "torch") -> torch.Tensor:
    """SSIM map of two ``[H, W, 3]`` (or ``[H, W, C]``) images in [0, 1].

    ``impl``: "torch" (five ``F.conv2d`` blurs, autograd backward: the reference) or "fused"
    (numba kernels with an analytic backward, :mod:`freescale_core.recon.fused_ssim`; same
    value within float32 rounding; CPU tensors only, others fall back to "torch").

    Returns:
        ``[C, H - 10, W - 10]`` per-channel SSIM over the valid window positions.
    """
    if img.shape != ref.shape or img.ndim != 3:
        raise ValueError(f"ssim: images must both be [H, W, C]; got {tuple(img.shape)} and "
                         f"{tuple(ref.shape)}")
    if min(img.shape[0], img.shape[1]) < SSIM_WINDOW:
        raise ValueError(f"ssim: image {tuple(img.shape[:2])} smaller than the "
                         f"{SSIM_WINDOW}x{SSIM_WINDOW} window")
    if impl not in ("torch", "fused"):
        raise ValueError(f"ssim: impl must be 'torch' or 'fused'; got {impl!r}")
    if impl == "fused" and img.device.type == "cpu" and ref.device.type == "cpu" \
            and img.dtype in (torch.float32, torch.float64):
        from freescale_core.recon.fused_ssim import fused_ssim_map

        return fused_ssim_map(img, ref)
    x = img.permute(2, 0, 1)[None]
    y = ref.permute(2, 0, 1)[None].to(x.dtype)
    w = gaussian_window(dtype=x.dtype).to(x.device)
    # (one grouped convolution over the five maps measured no faster: 541 vs 561 ms fwd+bwd at
    # 512x380, median of 5, benchmarks in docs/RECON.md; kept as five)
    mu_x, mu_y = _blur(x, w), _blur(y, w)
    sxx = _blur(x * x, w) - mu_x * mu_x
    syy = _blur(y * y, w) - mu_y * mu_y
    sxy = _blur(x * y, w) - mu_x * mu_y
    num = (2 * mu_x * mu_y + SSIM_C1) * (2 * sxy + SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + SSIM_C1) * (sxx + syy + SSIM_C2)
    return (num / den)[0]


def ssim(img: torch.Tensor, ref: torch.Tensor, impl: str = "torch") -> torch.Tensor:
    """Mean SSIM (scalar) of ``[H, W, C]`` images in [0, 1]; differentiable."""
    return ssim_map(img, ref, impl).mean()


def photometric_loss(img: torch.Tensor, ref: torch.Tensor, lambda_ssim: float = 0.2,
                     ssim_impl: str = "torch") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """3DGS loss ``(1 - lambda) L1 + lambda (1 - SSIM)`` of ``[H, W, 3]`` images.

    Returns:
        ``(loss, l1, ssim)`` scalars (l1 and ssim detached).
    """
    l1 = (img - ref).abs().mean()
    s = ssim(img, ref, ssim_impl) if lambda_ssim > 0 else torch.ones((), dtype=img.dtype)
    loss = (1.0 - lambda_ssim) * l1 + lambda_ssim * (1.0 - s)
    return loss, l1.detach(), s.detach()


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (inf for identical images)."""
    mse = float(((img.double() - ref.double()) ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def masked_photometric_loss(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None,
                            lambda_ssim: float = 0.2, ssim_impl: str = "torch") -> torch.Tensor:
    """``(1 - lambda) L1 + lambda (1 - SSIM)`` over the pixels where ``mask [H, W]`` is true
    (SSIM: the valid-window map cropped to the mask's centres); a floating-point ``mask`` is a
    per-pixel weight (:func:`weighted_photometric_loss`). ``mask=None``: every pixel,
    equal to :func:`photometric_loss`. ``ssim_impl``: see :func:`ssim_map`.

    Outside the mask both images are set to 0 before either term, so a masked-out pixel gets
    exactly zero gradient and the loss does not depend on what the reference shows there (an
    SSIM window at the mask's border sees the same constant in both)."""
    if mask is None:
        return photometric_loss(img, ref, lambda_ssim, ssim_impl)[0]
    if mask.is_floating_point():
        return weighted_photometric_loss(img, ref, mask, lambda_ssim, ssim_impl)
    m = mask.to(torch.bool)
    img = torch.where(m[..., None], img, torch.zeros((), dtype=img.dtype))
    ref = torch.where(m[..., None], ref.to(img.dtype), torch.zeros((), dtype=img.dtype))
    n = m.sum().clamp_min(1)
    l1 = ((img - ref).abs().sum(-1) * m).sum() / (n * img.shape[-1])
    if lambda_ssim <= 0:
        return l1
    h = SSIM_WINDOW // 2
    smap = ssim_map(img, ref, ssim_impl).mean(0)  # [H - 10, W - 10]
    mc = m[h:m.shape[0] - h, h:m.shape[1] - h]
    s = (smap * mc).sum() / mc.sum().clamp_min(1)
    return (1.0 - lambda_ssim) * l1 + lambda_ssim * (1.0 - s)


def weighted_photometric_loss(img: torch.Tensor, ref: torch.Tensor, weight: torch.Tensor,
                              lambda_ssim: float = 0.2, ssim_impl: str = "torch") -> torch.Tensor:
    """``(1 - lambda) L1 + lambda (1 - SSIM)`` with every pixel's term scaled by ``weight
    [H, W]`` (float, e.g. a fixer's confidence) and averaged over *all* pixels: ``weight = 1``
    is :func:`photometric_loss`, ``weight = c`` scales the loss by ``c``, and a pixel of weight
    0 gets no gradient from its own L1 term or from the SSIM window centred on it. A view whose
    weight is low everywhere therefore teaches little, not the same amount from fewer pixels
    (that is the boolean ``mask`` of :func:`masked_photometric_loss`)."""
    w = weight.to(img.dtype)
    l1 = ((img - ref.to(img.dtype)).abs().mean(-1) * w).mean()
    if lambda_ssim <= 0:
        return l1
    h = SSIM_WINDOW // 2
    smap = ssim_map(img, ref.to(img.dtype), ssim_impl).mean(0)  # [H - 10, W - 10]
    wc = w[h:w.shape[0] - h, h:w.shape[1] - h]
    return (1.0 - lambda_ssim) * l1 + lambda_ssim * ((1.0 - smap) * wc).mean()


def masked_psnr(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None
                ) -> float:
    """PSNR (dB) of ``[H, W, 3]`` images in [0, 1] over the pixels where ``mask`` is true
    (NaN for an empty mask); ``mask=None``: every pixel, as :func:`psnr`."""
    if mask is None:
        return psnr(img, ref)
    m = mask.to(torch.bool)
    if not bool(m.any()):
        return float("nan")
    d = (img.double() - ref.double())[m]
    mse = float((d ** 2).mean())
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def masked_psnr_ssim(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor | None = None
                     ) -> tuple[float, float]:
    """``(PSNR dB, SSIM)`` of ``[H, W, 3]`` images in [0, 1] over the pixels where ``mask``
    is true (SSIM: mean of the map over the mask's window centres; NaN for images smaller
    than the window or a mask with no centre). ``mask=None``: every pixel."""
    if mask is None:
        s = float(ssim(img, ref)) if min(ref.shape[:2]) >= SSIM_WINDOW else float("nan")
        return psnr(img, ref), s
    m = mask.to(torch.bool)
    if not bool(m.any()):
        return float("nan"), float("nan")
    p = masked_psnr(img, ref, m)
    if min(ref.shape[:2]) < SSIM_WINDOW:
        return p, float("nan")
    h = SSIM_WINDOW // 2
    mc = m[h:m.shape[0] - h, h:m.shape[1] - h]
    if not bool(mc.any()):
        return p, float("nan")
    smap = ssim_map(img.double(), ref.double()).mean(0)
    return p, float(smap[mc].mean())
