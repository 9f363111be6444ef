"""Held-out and training-view evaluation of trained Gaussians (PSNR / SSIM per view)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from freescale_core.geometry.cameras import Cameras
from freescale_core.recon.losses import masked_psnr_ssim
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.images import resize_area as _resize
from freescale_core.scene.scene import Scene


def _rasterize(*args, **kwargs):
    from freescale_core.raster import rasterize

    return rasterize(*args, **kwargs)


# =========================================================================== evaluation
def _render_np(g: Gaussians, cams: Cameras, j: int, bg, backend: str) -> np.ndarray:
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    with torch.no_grad():
        out = _rasterize(t(g.means), t(g.log_scales), t(g.quats_wxyz), t(g.opacity_logits),
                         t(g.sh), cams.world_from_cam[j], float(cams.fx[j]), float(cams.fy[j]),
                         float(cams.cx[j]), float(cams.cy[j]), int(cams.width[j]),
                         int(cams.height[j]), background=bg, backend=backend)
    return np.clip(out.rgb.detach().cpu().numpy(), 0.0, 1.0)


def _evaluate_views(g: Gaussians, cams: Cameras, images: Sequence[np.ndarray], bg,
                    backend: str = "auto", masks: Sequence[np.ndarray] | None = None) -> dict:
    """PSNR / SSIM per view; with ``masks`` over each view's mask pixels only."""
    ps, ss = [], []
    for j, img in enumerate(images):
        rgb = torch.from_numpy(_render_np(g, cams, j, bg, backend)).double()
        ref = torch.from_numpy(np.asarray(img)).double() / 255.0
        m = None if masks is None else torch.from_numpy(np.asarray(masks[j], bool))
        p, s_ = masked_psnr_ssim(rgb, ref, m)
        ps.append(p)
        ss.append(s_)
    return {"psnr": ps, "ssim": ss, "psnr_mean": float(np.mean(ps)) if ps else float("nan"),
            "ssim_mean": float(np.mean(ss)) if ss else float("nan")}


def evaluate(gaussians: Gaussians, scene: Scene, idx: Sequence[int] | np.ndarray,
             long_side: int | None = None, scale: float | None = None,
             background=(0.0, 0.0, 0.0), backend: str = "auto",
             masks: Sequence[np.ndarray] | None = None) -> dict:
    """PSNR and SSIM of rendered views against the scene's images (held-out evaluation).

    Args:
        gaussians: the reconstruction.
        scene: the scene (ground-truth images and cameras).
        idx: camera indices to evaluate, e.g. ``scene.split("ood")[1]``.
        long_side: evaluate at images downscaled so the long side is at most this (the
            training resolution of :func:`reconstruct` is ``stats["train_scale"]``); or
        scale: an explicit scale factor (overrides ``long_side``). Default: native size.
        background: RGB behind the Gaussians (use the training background).
        backend: rasterizer backend (see :func:`freescale_core.raster.rasterize`).
        masks: per view of ``idx``, a boolean mask at the evaluated size: score only its
            pixels (e.g. the co-visible ones, :mod:`freescale_core.eval.covis`); combined
            with the scene's object masks where it has them.
    Returns:
        ``{"views": [...], "psnr": [...], "ssim": [...], "psnr_mean", "ssim_mean",
        "resolution": [[w, h], ...], "masked"}``; SSIM as
        :func:`freescale_core.recon.losses.ssim` (11x11 Gaussian window, equal to skimage's).
        A scene with object masks is scored on the mask pixels only (``masked`` True): the
        background of an object capture is not part of the reconstruction.
    """
    idx = np.asarray(idx, np.int64).reshape(-1)
    cams = scene.cameras.subset(idx) if len(idx) else None
    if cams is None:
        return {"views": [], "psnr": [], "ssim": [], "psnr_mean": float("nan"),
                "ssim_mean": float("nan"), "resolution": []}
    if scale is None:
        long = np.maximum(cams.width, cams.height)
        scale = 1.0 if long_side is None else float(min(1.0, long_side / long.max()))
    cams = cams.scaled(scale)
    images = [_resize(scene.load_image(int(i)), cams.width[j], cams.height[j])
              for j, i in enumerate(idx)]
    given = masks
    masks = None
    if getattr(scene, "has_masks", False):
        from freescale_core.scene.io.masks import resize_mask

        masks = [resize_mask(scene.load_mask(int(i)), int(cams.width[j]), int(cams.height[j]))
                 for j, i in enumerate(idx)]
    if given is not None:
        if len(given) != len(idx):
            raise ValueError(f"{scene.scene_id}: {len(given)} masks for {len(idx)} views")
        for j, m in enumerate(given):
            if np.shape(m) != (int(cams.height[j]), int(cams.width[j])):
                raise ValueError(f"{scene.scene_id}: mask {j} is {np.shape(m)}, the view is "
                                 f"{int(cams.height[j])}x{int(cams.width[j])}")
        masks = [np.asarray(m, bool) if masks is None else np.asarray(m, bool) & masks[j]
                 for j, m in enumerate(given)]
    ev = _evaluate_views(gaussians, cams, images, tuple(background), backend, masks)
    ev["masked"] = masks is not None
    ev["views"] = idx.tolist()
    ev["resolution"] = [[int(w), int(h)] for w, h in zip(cams.width, cams.height)]
    return ev
