"""How much the training views' exposure differs, measured from the sparse points' colours.

A sparse point's colour is its source model's mean over the views that observed it. Seen by
view ``v`` at pixel ``p``, the ratio ``image_v(p) / colour`` is that view's colour gain times
noise (the point occluded in ``v``, a specular highlight, a point off its surface). The median
of the log ratios over the points a view sees is robust to such a minority, so it estimates the
view's log-gain per channel. The trainer caps the SH degree by the training views only when
the spread of these log-gains over the views exceeds ``ReconConfig.sh_cap_min_gain_std``.

Measured on the shared scenes' OOD training views (``lab/results/2026-12-04_stop36/recon.md``): llff_fern and kermit spread ~0.01 (exposure locked), strecha_fountain-P11
0.04, buddha 0.08 (hand-held, the camera's exposure moves), dtu_scan24 0.17 (its lights move
with the robot arm).
"""

from __future__ import annotations

import numpy as np

__all__ = ["gain_spread", "view_log_gains"]


def view_log_gains(cams, images, points_xyz: np.ndarray, points_rgb: np.ndarray, *,
                   min_points: int = 20, dark: int = 10, bright: int = 245) -> np.ndarray:
    """Per-view, per-channel log colour gain of each view against the points' colours.

    Args:
        cams: :class:`~freescale_core.geometry.cameras.Cameras` of the views (pixel centres
            at +0.5, the images' resolution).
        images: ``[H, W, 3]`` uint8 arrays or CPU tensors, one per camera.
        points_xyz: ``[P, 3]`` world points; points_rgb: ``[P, 3]`` uint8 colours.
        min_points: a view seeing fewer usable points gets a NaN row.
        dark, bright: samples with a channel of either the pixel or the point's colour outside
            ``[dark, bright]`` are not used (log of ~0, clipped highlights).
    Returns:
        ``[V, 3]`` float64: ``median(log(pixel) - log(colour))`` over the points each view sees
        in front of it and inside its image (nearest pixel); NaN rows where too few.
    """
    X = np.asarray(points_xyz, np.float64).reshape(-1, 3)
    C = np.asarray(points_rgb, np.float64).reshape(-1, 3)
    out = np.full((len(images), 3), np.nan)
    for v, img in enumerate(images):
        img = np.asarray(img)
        h, w = img.shape[:2]
        wfc = cams.world_from_cam[v]
        xc = (X - wfc[:3, 3]) @ wfc[:3, :3]  # R^T (X - t): camera coordinates
        z = xc[:, 2]
        front = z > 1e-9
        zs = np.where(front, z, 1.0)
        u = cams.fx[v] * xc[:, 0] / zs + cams.cx[v]
        y = cams.fy[v] * xc[:, 1] / zs + cams.cy[v]
        ok = front & (u >= 0) & (u < w) & (y >= 0) & (y < h)
        px = img[y[ok].astype(np.int64), u[ok].astype(np.int64)].astype(np.float64)
        c = C[ok]
        use = ((px.min(1) >= dark) & (px.max(1) <= bright)
               & (c.min(1) >= dark) & (c.max(1) <= bright))
        if int(use.sum()) >= min_points:
            out[v] = np.median(np.log(px[use]) - np.log(c[use]), axis=0)
    return out


def gain_spread(log_gains: np.ndarray, min_views: int = 3) -> float | None:
    """Standard deviation of the per-view log-gains over the measured views, mean of the three
    channels; None when fewer than ``min_views`` views were measured."""
    g = np.asarray(log_gains, np.float64)
    g = g[np.isfinite(g).all(1)]
    if len(g) < min_views:
        return None
    return float(g.std(0).mean())
