"""Co-visibility masks: which pixels of a held-out view some training view saw.

A held-out view of an extrapolating split (the OOD split's last views) can show surfaces no
training view saw; PSNR there measures a trainer's guess, not its reconstruction. Monocular
dynamic-view-synthesis evaluation (Gao et al. 2022, "Monocular Dynamic View Synthesis: A
Reality Check") scores only *co-visible* pixels for this reason. Here a held-out pixel is
co-visible when its surface point, lifted with the held-out view's depth, projects inside a
training view whose own depth there agrees within ``rel_tol`` (so it is not occluded).

The depths come from the sample scene's oracle where there is one (exact), and otherwise from a
*reference* reconstruction trained on every view of the scene, held-out ones included
(:func:`reference_depths`): it is used for the masks only, never by a trainer being scored, and
its depth at a held-out view is supervised by that view's photo. Pixels without a depth (the
reference's alpha under ``min_alpha``, or the oracle's sky) are left out unless
``no_depth_covered``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from freescale_core.geometry.cameras import Cameras


def backproject(cams: Cameras, j: int, depth: np.ndarray) -> np.ndarray:
    """World points ``[H * W, 3]`` of view ``j``'s pixel centres at camera-z ``depth [H, W]``."""
    H, W = depth.shape
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    d = depth.astype(np.float64)
    xc = np.stack([(xs - cams.cx[j]) / cams.fx[j] * d, (ys - cams.cy[j]) / cams.fy[j] * d, d], -1)
    wfc = cams.world_from_cam[j]
    return xc.reshape(-1, 3) @ wfc[:3, :3].T + wfc[:3, 3]


def covisible_masks(test: Cameras, test_depth: Sequence[np.ndarray], train: Cameras,
                    train_depth: Sequence[np.ndarray], rel_tol: float = 0.02,
                    no_depth_covered: bool = False, search_px: int = 0) -> list[np.ndarray]:
    """One boolean mask ``[H, W]`` per ``test`` view: True where a ``train`` view saw the pixel.

    Args:
        test, train: cameras; ``test_depth[j]`` / ``train_depth[i]`` are their camera-z depth
            maps at the cameras' sizes, ``<= 0`` (or non-finite) where unknown.
        rel_tol: depth agreement that counts as unoccluded, relative to the projected depth.
        no_depth_covered: count test pixels without a depth as covered (the oracle's sky,
            which every view sees at infinity) instead of leaving them out.
        search_px: also accept a training depth up to this many pixels from where the point
            lands (a reference's depth is noisy at edges and on fine relief).
    """
    if len(test_depth) != len(test) or len(train_depth) != len(train):
        raise ValueError(f"{len(test_depth)} / {len(train_depth)} depth maps for "
                         f"{len(test)} / {len(train)} cameras")
    tds = [np.where(np.isfinite(d), d, 0.0) for d in train_depth]
    out = []
    for j in range(len(test)):
        d = np.asarray(test_depth[j], np.float64)
        d = np.where(np.isfinite(d), d, 0.0)
        if d.shape != (int(test.height[j]), int(test.width[j])):
            raise ValueError(f"test depth {j} is {d.shape}, camera is "
                             f"{int(test.height[j])}x{int(test.width[j])}")
        has = d.reshape(-1) > 0
        X = backproject(test, j, np.maximum(d, 1e-6))[has]
        seen = np.zeros(len(X), bool)
        if len(X):
            uv, z = train.project(X)
            for i in range(len(train)):
                w, h = int(train.width[i]), int(train.height[i])
                u, v, zi = uv[i, :, 0], uv[i, :, 1], z[i]
                ok = (zi > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
                ui = np.clip(np.where(ok, u, 0).astype(np.int64), 0, w - 1)
                vi = np.clip(np.where(ok, v, 0).astype(np.int64), 0, h - 1)
                for dy in range(-search_px, search_px + 1):
                    for dx in range(-search_px, search_px + 1):
                        dt = tds[i][np.clip(vi + dy, 0, h - 1), np.clip(ui + dx, 0, w - 1)]
                        seen |= ok & (dt > 0) & (np.abs(dt - zi) <= rel_tol * zi)
        m = np.full(d.size, bool(no_depth_covered))
        m[has] = seen
        out.append(m.reshape(d.shape))
    return out


def reference_depths(gaussians, cams: Cameras, min_alpha: float = 0.5,
                     backend: str = "auto") -> list[np.ndarray]:
    """Rendered camera-z depth of ``gaussians`` at each camera; 0 where alpha < ``min_alpha``."""
    from freescale_core.raster import render_gaussians

    out = []
    for j in range(len(cams)):
        _, depth, alpha = render_gaussians(
            gaussians, cams.world_from_cam[j], float(cams.fx[j]), float(cams.fy[j]),
            float(cams.cx[j]), float(cams.cy[j]), int(cams.width[j]), int(cams.height[j]),
            backend=backend)
        out.append(np.where(alpha >= min_alpha, depth, 0.0).astype(np.float32))
    return out


def split_masks(scene, split: str, scale: float, reference, rel_tol: float = 0.05,
                min_alpha: float = 0.5, backend: str = "auto", search_px: int = 0
                ) -> list[np.ndarray]:
    """Co-visibility masks of ``scene.split(split)``'s held-out views, cameras scaled by
    ``scale``, cut with the depths of the ``reference`` Gaussians (trained on every view)."""
    train, test = scene.split(split)
    tr = scene.cameras.subset(train).scaled(scale)
    te = scene.cameras.subset(test).scaled(scale)
    return covisible_masks(te, reference_depths(reference, te, min_alpha, backend), tr,
                           reference_depths(reference, tr, min_alpha, backend), rel_tol=rel_tol,
                           search_px=search_px)


__all__ = ["backproject", "covisible_masks", "reference_depths", "split_masks"]
