"""Keeping Gaussians in the scene: a robust bound from the cameras and sparse points the
trainer was given, and the rules that flag Gaussians to relocate.

Nothing in the photometric loss keeps a Gaussian near the scene: a near-transparent one
wanders with the MCMC position noise, a large one grows, and once outside every view it gets
no gradient back. Far Gaussians then inflate everything sized from the Gaussians downstream
(the certainty grid's box swallowed every candidate of an outdoor facade). The bound:

* centre and half-diagonal ``R`` of the box spanned by the camera centres and the
  ``[q, 1 - q]`` per-axis quantiles of the sparse points (robust to stray SfM points);
* a Gaussian *escaped* when its centre is farther than ``margin * R`` from the centre;
* *too large* (3DGS world-space pruning) when its largest std-dev exceeds
  ``world_scale * R``;
* *too large on screen* (3DGS screen-size pruning) when, in the current training view, its
  3-sigma radius exceeds ``screen_frac`` of the image's long side (a floater filling the view);
* *seen by too few views* when its centre lies in front of and inside the image of fewer than
  ``min_views`` training cameras (optionally: and its largest std-dev exceeds ``min_views_size``
  times the median one). A Gaussian one view alone sees has a depth no second view
  constrains: it can sit anywhere along that view's rays, and on strecha_fountain-P11 such
  Gaussians (1% of them) spread into a haze over its farthest held-out view
  (docs/RECON.md, stop 25).

Flagged Gaussians are relocated onto live ones (MCMC relocation, so the count is kept) by the
strategy. :func:`extent_report` measures the problem (share of Gaussians beyond 5 R and the
farthest multiple of R).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class SceneBounds:
    """Sphere around the cameras and sparse points: ``centre [3]``, half-diagonal ``radius``."""

    centre: np.ndarray
    radius: float

    @classmethod
    def from_inputs(cls, camera_centres: np.ndarray, points_xyz: np.ndarray | None,
                    quantile: float = 0.02) -> "SceneBounds":
        """Box of the camera centres ``[C, 3]`` and the points' ``[quantile, 1 - quantile]``
        per-axis range (non-finite points ignored); its centre and half-diagonal."""
        parts = [np.asarray(camera_centres, np.float64).reshape(-1, 3)]
        if points_xyz is not None and len(points_xyz):
            p = np.asarray(points_xyz, np.float64).reshape(-1, 3)
            p = p[np.all(np.isfinite(p), axis=1)]
            if len(p):
                parts.append(np.quantile(p, [quantile, 1.0 - quantile], axis=0))
        allp = np.concatenate(parts)
        lo, hi = allp.min(0), allp.max(0)
        radius = float(np.linalg.norm(hi - lo) / 2.0)
        return cls((lo + hi) / 2.0, max(radius, 1e-6))

    def distance(self, means: np.ndarray | torch.Tensor) -> np.ndarray:
        """``[N]`` distances of the centres ``[N, 3]`` from the bound's centre, in units of R."""
        m = means.detach().double().numpy() if isinstance(means, torch.Tensor) else np.asarray(
            means, np.float64)
        return np.linalg.norm(m - self.centre, axis=1) / self.radius


def views_seeing(means: np.ndarray | torch.Tensor, cams) -> np.ndarray:
    """``[N]`` number of cameras of ``cams`` (a :class:`~freescale_core.geometry.cameras.Cameras`)
    whose image contains the projection of each centre ``[N, 3]`` in front of the camera."""
    m = means.detach().double().numpy() if isinstance(means, torch.Tensor) else np.asarray(
        means, np.float64)
    count = np.zeros(len(m), np.int64)
    for i in range(len(cams)):  # one camera at a time: [N] temporaries, not [C, N]
        uv, z = cams.subset([i]).project(m)
        u, v, z = uv[0, :, 0], uv[0, :, 1], z[0]
        count += (z > 0) & (u >= 0) & (u < cams.width[i]) & (v >= 0) & (v < cams.height[i])
    return count


def flag_outliers(params: dict, bounds: SceneBounds, margin: float | None,
                  world_scale: float | None, screen_frac: float | None = None,
                  camera=None, min_views: int | None = None, cams=None,
                  min_views_size: float | None = None) -> dict[str, np.ndarray]:
    """Rows to relocate: ``{"escaped", "world_scale", "screen", "few_views"}`` index arrays
    (may overlap).

    Args:
        params: the trainer's parameter dict (``means``, ``log_scales``).
        margin: escape radius in units of ``bounds.radius`` (None: no check).
        world_scale: largest std-dev limit in units of ``bounds.radius`` (None: no check).
        screen_frac: 3-sigma screen radius limit as a fraction of the long side (None: none).
        camera: the current view's camera (``world_from_cam``, ``fx``, ``fy``, ``width``,
            ``height``) for the screen check.
        min_views: flag centres that fewer than this many of ``cams`` see (None: no check).
        cams: the training cameras for ``min_views``.
        min_views_size: flag those only when their largest std-dev exceeds this many times
            the median largest std-dev of all Gaussians (None: whatever their size).
    """
    empty = np.zeros(0, np.int64)
    out = {"escaped": empty, "world_scale": empty, "screen": empty, "few_views": empty}
    with torch.no_grad():
        means = params["means"].data.double()
        smax = torch.exp(params["log_scales"].data.double().max(dim=1).values)
        if margin is not None:
            d = torch.linalg.norm(means - torch.from_numpy(bounds.centre), dim=1)
            out["escaped"] = torch.nonzero(~(d <= margin * bounds.radius)).flatten().numpy()
        if world_scale is not None:
            out["world_scale"] = torch.nonzero(~(smax <= world_scale * bounds.radius)
                                               ).flatten().numpy()
        if screen_frac is not None and camera is not None:
            T = torch.as_tensor(np.asarray(camera.world_from_cam, np.float64))
            z = (means - T[:3, 3]) @ T[:3, 2]
            f = max(float(camera.fx), float(camera.fy))
            long_side = max(int(camera.width), int(camera.height))
            near = z > 1e-6
            r = torch.where(near, 3.0 * smax * f / z.clamp_min(1e-6), torch.zeros_like(z))
            out["screen"] = torch.nonzero(near & (r > screen_frac * long_side)).flatten().numpy()
        if min_views is not None and cams is not None and len(means):
            # the size condition first: only the large Gaussians need projecting
            s = smax.numpy()
            rows = (np.arange(len(s)) if min_views_size is None else
                    np.nonzero(s > min_views_size * np.median(s))[0])
            out["few_views"] = rows[views_seeing(means[rows], cams) < min_views]
    return out


def extent_report(means: np.ndarray, bounds: SceneBounds, beyond: float = 5.0) -> dict:
    """``{"share_beyond", "beyond", "farthest", "n"}``: share of centres farther than
    ``beyond`` R from the bound's centre, and the farthest distance in units of R."""
    d = bounds.distance(means)
    d = np.where(np.isfinite(d), d, np.inf)
    return {"n": int(len(d)), "beyond": beyond,
            "share_beyond": float(np.mean(d > beyond)) if len(d) else 0.0,
            "farthest": float(d.max()) if len(d) else 0.0}
