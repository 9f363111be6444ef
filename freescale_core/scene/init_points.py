"""Initial points for a scene without sparse points (instant-ngp / Blender captures).

A reconstruction starts from points. When the capture has none, :func:`random_init_points`
draws them uniformly inside the *view volume*: the capture's box (instant-ngp's
``aabb_scale`` box when the transforms.json gives one, recorded by the reader as
``Scene.extras["aabb_box"]``; else a sphere around the point the cameras look at, with the
cameras' median distance as radius), keeping only points that at least ``min_views``
cameras see in front of them and inside their image. Each point takes the colour of its
pixel in one camera that sees it. Deterministic for a seed.
"""

from __future__ import annotations

import numpy as np

from freescale_core.errors import DegenerateSceneError

__all__ = ["view_volume", "random_init_points"]


def _look_at_point(centers: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Least-squares point closest to every camera's optical axis."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, dirs):
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    try:
        return np.linalg.solve(A, b)
    except np.linalg.LinAlgError:
        return centers.mean(axis=0)


def view_volume(scene) -> tuple[np.ndarray, np.ndarray, str]:
    """``(lo [3], hi [3], how)``: the box random initial points are drawn from."""
    box = scene.extras.get("aabb_box")
    if box is not None:
        lo, hi = (np.asarray(x, dtype=np.float64) for x in box)
        return lo, hi, f"aabb_scale box {np.round(hi - lo, 3).tolist()}"
    cams = scene.cameras
    c = cams.centers
    dirs = cams.world_from_cam[:, :3, 2]
    p = _look_at_point(c, dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    r = float(np.median(np.linalg.norm(c - p, axis=1)))
    if not np.isfinite(r) or r <= 0:
        r = float(np.linalg.norm(c.max(axis=0) - c.min(axis=0))) or 1.0
    return p - r, p + r, f"sphere of radius {r:.3g} around the cameras' look-at point"


def random_init_points(scene, n: int, rng: np.random.Generator, min_views: int = 2,
                       max_cams: int = 16) -> tuple[np.ndarray, np.ndarray, str]:
    """``(xyz [n, 3] float64, rgb [n, 3] uint8, reason)`` drawn in the view volume."""
    lo, hi, how = view_volume(scene)
    cams = scene.cameras
    N = len(cams)
    pick = np.unique(np.linspace(0, N - 1, min(N, max_cams)).round().astype(int))
    sub = cams.subset(pick)
    need = min(min_views, len(pick))
    pts, owner, pix = [], [], []
    have = 0
    for _ in range(50):
        x = rng.uniform(lo, hi, size=(max(4 * n, 1000), 3))
        uv, z = sub.project(x)
        inside = ((z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 1] >= 0)
                  & (uv[..., 0] < sub.width[:, None]) & (uv[..., 1] < sub.height[:, None]))
        ok = inside.sum(axis=0) >= need
        if ok.any():
            first = np.argmax(inside[:, ok], axis=0)
            pts.append(x[ok])
            owner.append(first)
            pix.append(uv[first, np.flatnonzero(ok)])
            have += int(ok.sum())
        if have >= n:
            break
    if have < 4:
        raise DegenerateSceneError(
            scene.scene_id, f"no sparse points, and no random point in the view volume ({how})"
            f" is seen by {need} cameras: the cameras do not look at a common region",
            scene.root)
    xyz = np.concatenate(pts)[:n]
    own = np.concatenate(owner)[:n]
    uv = np.concatenate(pix)[:n]
    rgb = np.zeros((len(xyz), 3), np.uint8)
    for k in np.unique(own):
        img = scene.load_image(int(pick[k]))
        m = own == k
        h, w = img.shape[:2]
        sx, sy = w / float(sub.width[k]), h / float(sub.height[k])
        u = np.clip((uv[m, 0] * sx).astype(int), 0, w - 1)
        v = np.clip((uv[m, 1] * sy).astype(int), 0, h - 1)
        rgb[m] = img[v, u, :3]
    return xyz, rgb, (f"no sparse points: {len(xyz)} random points in the view volume ({how}),"
                      f" each seen by >= {need} of {len(pick)} cameras")
