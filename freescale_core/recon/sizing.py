"""The sizing rules of the reconstruction: training resolution, Gaussian budget, SH degree,
the loss-EMA plateau test and the learning-rate schedule (docs/RECON.md, "Sizing to the
scene"). Pure functions, each unit-tested; every decision's reason goes to
``stats["reasons"]``."""

from __future__ import annotations

from typing import Sequence
import math

import numpy as np

from freescale_core.geometry.cameras import Cameras
from freescale_core.scene.gaussians import Gaussians
from schemas.recon import ReconConfig



# =========================================================================== sizing rules
def image_peak(image: np.ndarray, q: float = 99.5) -> float:
    """The image's own white level: the ``q``-th percentile of its values (uint8 scale, at
    least 1). A well-exposed photo is close to 255; a dark capture far below it."""
    return float(max(1.0, np.percentile(image, q)))


def roundtrip_psnr(image: np.ndarray, factor: int, peak: float = 255.0) -> float:
    """PSNR (dB) of ``image [H, W, 3]`` uint8 against itself downscaled by ``factor`` (area)
    and upscaled back (bicubic), with ``peak`` as the signal's full scale: high means the
    image holds no detail at the finer scale."""
    import cv2

    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, w // factor), max(1, h // factor)),
                       interpolation=cv2.INTER_AREA)
    back = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    mse = np.mean((image.astype(np.float64) - back.astype(np.float64)) ** 2) / float(peak) ** 2
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def choose_resolution(widths: Sequence[int], heights: Sequence[int], cfg: ReconConfig,
                      sample_images: Sequence[np.ndarray] = ()) -> tuple[float, str]:
    """Resolution rule: one scale factor for all training images of a scene.

    1. cap: ``s = min(1, max_long_side / longest side)``;
    2. detail: if ``cfg.detail_psnr_db`` is set, divide ``s`` by the largest factor ``f`` in
       ``cfg.detail_factors`` for which every sample image (already at scale ``s``) survives a
       down-by-``f``/up round trip above ``detail_psnr_db`` (blurry or upsampled captures).
       The PSNR is taken against each image's own white level (:func:`image_peak`), not 255:
       a dark capture's detail is small in grey levels but not absent (on kermit scaled to
       15% brightness the 255-scale test read 42 dB at x2 and downscaled; against its white
       level it reads 25 dB, like the original's 26).

    Args:
        widths, heights: ``[N]`` native image sizes.
        sample_images: a few ``[H, W, 3]`` uint8 training images at native size.
    Returns:
        ``(scale, reason)``.
    """
    import cv2

    long_side = int(max(max(widths), max(heights)))
    s = min(1.0, cfg.max_long_side / long_side)
    reason = (f"long side {long_side} px <= cap {cfg.max_long_side}: native size" if s == 1.0
              else f"long side {long_side} px > cap {cfg.max_long_side}: scale {s:.4f}")
    if cfg.detail_psnr_db is None or not len(sample_images):
        return s, reason
    scaled = []
    for img in sample_images:
        h, w = img.shape[:2]
        scaled.append(img if s == 1.0 else cv2.resize(
            img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA))
    best, best_db, stop = 1, None, ""
    for f in sorted(cfg.detail_factors):
        if min(min(im.shape[:2]) for im in scaled) // f < 16:
            break
        db = min(roundtrip_psnr(im, f, image_peak(im)) for im in scaled)
        if db < cfg.detail_psnr_db:
            stop = (f"down-up x{f} round trip {db:.1f} dB < {cfg.detail_psnr_db:g} dB: "
                    f"detail at this scale")
            break
        best, best_db = f, db
    if best > 1:
        reason += (f"; down-up x{best} round trip {best_db:.1f} dB >= {cfg.detail_psnr_db:g} dB: "
                   f"no detail lost, downscale by {best}")
    if stop:
        reason += f"; {stop}"
    return s / best, reason


def choose_budget(n_points: int, n_views: int, pixels_per_view: float, cfg: ReconConfig
                  ) -> tuple[int, str]:
    """Budget rule: ``clamp(max(k_p * points, pixels / p_g), budget_min, cap_gaussians)``.

    ``k_p = cfg.budget_per_point`` (Gaussians per sparse point: geometric detail found by SfM),
    ``p_g = cfg.budget_pixels_per_gaussian`` (training pixels per Gaussian: texture detail).

    Args:
        n_points: sparse SfM points. n_views: training views.
        pixels_per_view: mean pixels of one training image at the training resolution.
    Returns:
        ``(budget, reason)``.
    """
    from_points = cfg.budget_per_point * n_points
    total_px = n_views * pixels_per_view
    from_pixels = total_px / cfg.budget_pixels_per_gaussian
    raw = max(from_points, from_pixels)
    budget = int(min(max(raw, cfg.budget_min), cfg.cap_gaussians))
    driver = "points" if from_points >= from_pixels else "pixels"
    reason = (f"max({cfg.budget_per_point:g} x {n_points} points = {int(from_points)}, "
              f"{total_px:.0f} px / {cfg.budget_pixels_per_gaussian:g} = {int(from_pixels)}) "
              f"-> {int(raw)} ({driver})")
    if budget != int(raw):
        reason += (f", clamped to [{cfg.budget_min}, {cfg.cap_gaussians}] -> {budget}")
    return budget, reason


def choose_sh_degree(n_views: int, cfg: ReconConfig,
                     gain_spread: float | None = None) -> tuple[int, str]:
    """Highest SH degree the training views can constrain: ``cfg.sh_degree`` capped at the
    largest ``d`` with ``cfg.sh_views_per_coeff * (d + 1) ** 2 <= n_views``, never below 1.

    Degree ``d`` gives each Gaussian ``(d + 1) ** 2`` colour coefficients per channel; a
    Gaussian that fewer views see than a small multiple of that can fit the training views
    with colour that no other direction shares. ``sh_views_per_coeff=None`` keeps
    ``cfg.sh_degree``.

    With ``cfg.sh_cap_min_gain_std = t`` the cap applies only when the training views'
    exposure disagrees: ``gain_spread`` (the std of their log colour gains,
    :func:`freescale_core.recon.photometric.gain_spread`) above ``t``, or None (not
    measurable: the cap applies, as without the rule). On the five shared scenes this caps
    exactly the one the cap helped (buddha); the supposed reason, that high-degree SH fits
    each photo's exposure, was not supported by a test on painted sample scenes, so the rule
    is an empirical one (docs/RECON.md, "The SH cap only where the views disagree").

    Returns:
        ``(degree, reason)``.
    """
    if cfg.sh_views_per_coeff is None:
        return cfg.sh_degree, f"max {cfg.sh_degree} (no view-count cap)"
    t = cfg.sh_cap_min_gain_std
    if t is not None and gain_spread is not None and gain_spread <= t:
        return cfg.sh_degree, (f"max {cfg.sh_degree}: view-count cap off, the training views' "
                               f"log colour gain std {gain_spread:.3f} <= {t:g}")
    d = 0
    while d < 3 and cfg.sh_views_per_coeff * (d + 2) ** 2 <= n_views:
        d += 1
    deg = min(cfg.sh_degree, max(1, d))
    k = cfg.sh_views_per_coeff
    holds = f"up to d = {d}" if k <= n_views else "for no d"
    why = ("" if t is None else
           f"; log colour gain std {gain_spread:.3f} > {t:g}" if gain_spread is not None else
           "; log colour gain spread not measurable")
    return deg, (f"max {deg}: {n_views} training views, {k:g} x (d+1)^2 <= {n_views} holds "
                 f"{holds} (at least 1, at most {cfg.sh_degree}){why}")


def ema_series(losses: Sequence[float], halflife: float) -> np.ndarray:
    """Exponential moving average ``[T]`` of ``losses [T]`` with the given half-life (steps),
    bias-corrected so early values are not pulled towards 0."""
    beta = 0.5 ** (1.0 / halflife)
    out = np.empty(len(losses))
    m, w = 0.0, 0.0
    for i, x in enumerate(losses):
        m = beta * m + (1 - beta) * float(x)
        w = beta * w + (1 - beta)
        out[i] = m / w
    return out


def plateau_reached(ema: Sequence[float], window: int, tol: float) -> bool:
    """Plateau rule: the loss EMA improved by less than ``tol`` (relative) over ``window`` steps.

    Args:
        ema: ``[T]`` loss EMA up to now (one value per step).
    Returns:
        False while fewer than ``window + 1`` values exist.
    """
    if len(ema) <= window:
        return False
    prev, now = float(ema[-1 - window]), float(ema[-1])
    return (prev - now) < tol * max(abs(prev), 1e-12)


def scene_extent(cameras: Cameras, points_xyz: np.ndarray | None = None) -> float:
    """3DGS ``spatial_lr_scale``: 1.1 x the largest camera distance from the camera centroid
    (falls back to the sparse points' spread when all cameras coincide)."""
    c = cameras.centers
    r = float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) if len(c) else 0.0
    if r < 1e-9 and points_xyz is not None and len(points_xyz):
        r = float(np.max(np.linalg.norm(points_xyz - points_xyz.mean(0), axis=1)))
    return 1.1 * max(r, 1e-6)


def means_lr(progress: float, cfg: ReconConfig, extent: float) -> float:
    """3DGS exponential decay from ``lr_means_init`` (progress 0) to ``lr_means_final`` (1),
    times the scene extent."""
    return extent * exp_decay(cfg.lr_means_init, cfg.lr_means_final, progress)


def exp_decay(start: float, end: float, progress: float) -> float:
    """3DGS's learning-rate decay: log-linear from ``start`` (progress 0) to ``end`` (1)."""
    p = min(max(progress, 0.0), 1.0)
    return math.exp((1 - p) * math.log(start) + p * math.log(end))
