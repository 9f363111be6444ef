"""Candidate camera placement (METHOD.md stage 3).

Ten trajectory modes around anchors chosen among the training cameras:

* object-centric, looking at a point sampled from high-certainty voxels of the central part
  of the certainty grid (the authors' pool was always empty; here it is drawn from the grid):
  ``orbit`` (arc about the up axis through the look-at point, offset scaled toward it),
  ``spiral`` (LLFF-style spiral around the anchor in its image plane), ``lemniscate`` (figure
  eight on the sphere about the look-at point), ``dolly_in`` / ``dolly_out`` (move along the
  line to the look-at point while scaling the focal length by the same ratio, so the target
  keeps its image size: a dolly zoom);
* path-following: ``interpolation`` (cubic spline through the training centres in capture
  order, rotations by slerp), ``move_up`` / ``move_down`` (world up), ``move_left`` /
  ``move_right`` (camera right, made horizontal), keeping the anchor's orientation.

Anchors are jittered (position N(0, sigma^2), sigma ~ U[0, 0.1] scene units; rotation about a
random axis within +-20 deg) and then a random subset of all candidates is perturbed
(sigma ~ U[0, 0.5], +-30 deg). Up = -(mean camera y axis), OpenCV y pointing down. Intrinsics
are the anchor's (focal scaled for dolly). Every random draw comes from generators seeded by
``(seed, mode id)``, so the same seed gives the same cameras.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.select import TRAJECTORY_MODES, CandidateConfig

from freescale_core.geometry.cameras import (Cameras, look_at, make_pose, quat_wxyz_to_rotmat, rotmat_to_quat_wxyz,
                      slerp_wxyz)
from freescale_core.select.certainty import CertaintyGrid

__all__ = ["CandidateSet", "generate_candidates", "world_up", "scene_scale", "select_anchors",
           "lookat_pool", "central_region", "axis_angle_rotmat", "random_rotations",
           "OBJECT_CENTRIC_MODES"]

OBJECT_CENTRIC_MODES = ("orbit", "spiral", "lemniscate", "dolly_in", "dolly_out")


@dataclass
class CandidateSet:
    """Candidate cameras with their provenance.

    Attributes:
        cameras: N candidate cameras.
        mode: ``[N]`` str trajectory mode.
        traj_id: ``[N]`` int trajectory id (unique over modes).
        frame_idx: ``[N]`` int frame index within its trajectory (0 .. L-1).
        anchor_idx: ``[N]`` int training camera the trajectory was built from.
        lookat: ``[N, 3]`` look-at point (NaN for modes without one).
        perturbed: ``[N]`` bool: got the random extra perturbation.
        scale: scene-scale unit (world units) used for every length.
        up: ``[3]`` world up vector.
        lookat_pool_size: number of voxels in the look-at pool (0 = fell back).
        lookat_fallback: "" or why the pool fell back.
    """

    cameras: Cameras
    mode: np.ndarray
    traj_id: np.ndarray
    frame_idx: np.ndarray
    anchor_idx: np.ndarray
    lookat: np.ndarray
    perturbed: np.ndarray
    scale: float
    up: np.ndarray
    lookat_pool_size: int
    lookat_fallback: str = ""

    def __len__(self) -> int:
        return len(self.cameras)


# ---------------------------------------------------------------------- small helpers
def world_up(train_cams: Cameras) -> np.ndarray:
    """``[3]`` up = -(mean camera y axis) (OpenCV y points down), unit length."""
    y = train_cams.world_from_cam[:, :3, 1].mean(axis=0)
    n = np.linalg.norm(y)
    if n < 1e-6:  # cameras with every roll: fall back to the first camera's up
        y = train_cams.world_from_cam[0, :3, 1]
        n = np.linalg.norm(y)
    return -y / n


def scene_scale(train_cams: Cameras, grid: CertaintyGrid, unit: str) -> float:
    """The length unit of the candidate stage (see ``CandidateConfig.scale_unit``).

    Returns a positive float; when the chosen unit is 0 (one camera, coincident cameras) it
    falls back to 5% of the box diagonal.
    """
    c = train_cams.centers
    if unit == "box_diagonal":
        s = grid.diagonal
    elif unit == "camera_radius":
        s = float(np.median(np.linalg.norm(c - c.mean(axis=0), axis=1)))
    elif unit == "camera_spacing":
        if len(c) < 2:
            s = 0.0
        else:
            d = np.linalg.norm(c[:, None] - c[None], axis=-1)
            np.fill_diagonal(d, np.inf)
            s = float(np.median(d.min(axis=1)))
    else:
        raise ValueError(f"unknown scale_unit {unit!r}")
    if not np.isfinite(s) or s <= 1e-12 * max(1.0, grid.diagonal):
        s = 0.05 * grid.diagonal
    return float(s)


def axis_angle_rotmat(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: ``axis [..., 3]`` (any length > 0), ``angle [...]`` rad -> ``[..., 3, 3]``."""
    axis = np.asarray(axis, dtype=np.float64)
    angle = np.asarray(angle, dtype=np.float64)
    axis, angle = np.broadcast_arrays(axis, angle[..., None])
    angle = angle[..., 0]
    k = axis / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-12)
    x, y, z = k[..., 0], k[..., 1], k[..., 2]
    K = np.zeros(k.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -z, y
    K[..., 1, 0], K[..., 1, 2] = z, -x
    K[..., 2, 0], K[..., 2, 1] = -y, x
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def random_rotations(n: int, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """``[n, 3, 3]`` rotations about uniform random axes by angles uniform in +-max_deg."""
    axis = rng.normal(size=(n, 3))
    ang = np.radians(rng.uniform(-max_deg, max_deg, size=n))
    return axis_angle_rotmat(axis, ang)


def _kmeans_anchors(x: np.ndarray, k: int, rng: np.random.Generator, iters: int = 25) -> np.ndarray:
    """k-means++ then Lloyd on ``x [n, 3]``; returns the index of the point nearest each mean."""
    n = x.shape[0]
    centers = [x[rng.integers(n)]]
    d2 = np.sum((x - centers[0]) ** 2, axis=1)
    for _ in range(1, k):
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(n, 1.0 / n)
        centers.append(x[rng.choice(n, p=p)])
        d2 = np.minimum(d2, np.sum((x - centers[-1]) ** 2, axis=1))
    C = np.array(centers)
    for _ in range(iters):
        lab = np.argmin(np.sum((x[:, None] - C[None]) ** 2, axis=-1), axis=1)
        cnt = np.bincount(lab, minlength=k)
        sums = np.stack([np.bincount(lab, weights=x[:, d], minlength=k) for d in range(3)], 1)
        newC = np.where(cnt[:, None] > 0, sums / np.maximum(cnt, 1)[:, None], C)
        if np.allclose(newC, C):
            break
        C = newC
    idx = np.argmin(np.sum((x[:, None] - C[None]) ** 2, axis=-1), axis=0)
    return idx


def _fps_anchors(x: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    n = x.shape[0]
    out = [int(rng.integers(n))]
    d2 = np.sum((x - x[out[0]]) ** 2, axis=1)
    for _ in range(1, k):
        j = int(np.argmax(d2))
        out.append(j)
        d2 = np.minimum(d2, np.sum((x - x[j]) ** 2, axis=1))
    return np.array(out)


def select_anchors(centers: np.ndarray, n: int, method: str,
                   rng: np.random.Generator) -> np.ndarray:
    """``[n]`` training camera indices used as anchors (K-Means or FPS on centres).

    With fewer distinct centres than ``n``, every distinct camera is used once and the rest
    are drawn at random (with replacement).
    """
    x = np.asarray(centers, dtype=np.float64)
    _, first = np.unique(np.round(x, 12), axis=0, return_index=True)
    uniq = np.sort(first)
    if len(uniq) <= n:
        extra = rng.choice(len(x), size=n - len(uniq), replace=True)
        return np.concatenate([uniq, extra]).astype(np.int64)
    xs = x[uniq]
    sel = _kmeans_anchors(xs, n, rng) if method == "kmeans" else _fps_anchors(xs, n, rng)
    sel = uniq[sel]
    # k-means may map two clusters to one camera: fill duplicates with farthest points
    _, keep = np.unique(sel, return_index=True)
    sel = sel[np.sort(keep)]
    while len(sel) < n:
        d2 = np.min(np.sum((x[:, None] - x[sel][None]) ** 2, axis=-1), axis=1)
        sel = np.append(sel, int(np.argmax(d2)))
    return sel.astype(np.int64)


def central_region(grid: CertaintyGrid, central_fraction: float) -> np.ndarray:
    """The central part of the scene: ``[P, 3]`` indices of non-empty voxels.

    The voxels nearest to the certainty-weighted median point (per-axis weighted median)
    that together hold ``central_fraction`` of the total certainty. Robust to far floaters
    that stretch the box, and never empty for a non-empty grid (a hollow object whose
    centre is empty still gives its nearest surfaces).
    """
    idx, centers, C = grid.nonzero()
    if len(idx) == 0:
        return idx
    med = np.empty(3)
    for ax in range(3):
        o = np.argsort(centers[:, ax], kind="stable")
        cdf = np.cumsum(C[o])
        med[ax] = centers[o[np.searchsorted(cdf, 0.5 * cdf[-1])], ax]
    d = np.linalg.norm((centers - med) / grid.voxel_size, axis=1)
    o = np.lexsort((np.arange(len(d)), d))
    cdf = np.cumsum(C[o])
    k = int(np.searchsorted(cdf, central_fraction * cdf[-1])) + 1
    return idx[o[:min(k, len(o))]]


def lookat_pool(grid: CertaintyGrid, central_fraction: float,
                quantile: float) -> tuple[np.ndarray, str]:
    """Voxels look-at points are drawn from: high certainty in the central region.

    Central region: :func:`central_region`; high certainty = C >= the ``quantile`` of that
    region's voxels.

    Returns:
        ``(idx [P, 3] int64, fallback)``; ``fallback`` is "" normally, or why the pool is
        empty (an empty grid: look-at = box centre).
    """
    reg = central_region(grid, central_fraction)
    if len(reg) == 0:
        return np.zeros((0, 3), np.int64), "empty grid: look-at = box centre"
    vals = grid.values[reg[:, 0], reg[:, 1], reg[:, 2]]
    return reg[vals >= np.quantile(vals, quantile)].astype(np.int64), ""


def _sample_lookat(grid: CertaintyGrid, pool: np.ndarray, n: int,
                   rng: np.random.Generator) -> np.ndarray:
    """``[n, 3]`` points uniform inside voxels drawn uniformly from ``pool``."""
    if len(pool) == 0:
        return np.tile(0.5 * (grid.bbox_min + grid.bbox_max), (n, 1))
    v = pool[rng.integers(len(pool), size=n)]
    return grid.bbox_min + (v + rng.uniform(0.05, 0.95, size=(n, 3))) * grid.voxel_size


def _rot_look(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    return look_at(eye, target, up)[..., :3, :3]


def _safe_offset(a: np.ndarray, p: np.ndarray, fwd: np.ndarray, scale: float) -> np.ndarray:
    """``a - p``, replaced by ``-forward * scale`` where the anchor sits on its target."""
    off = a - p
    bad = np.linalg.norm(off, axis=-1) < 1e-9 * max(scale, 1e-12)
    return np.where(bad[:, None], -fwd * scale, off)


# ---------------------------------------------------------------------- modes
def _mode_paths(mode: str, a_pos: np.ndarray, a_R: np.ndarray, p: np.ndarray, L: int,
                cfg: CandidateConfig, up: np.ndarray, scale: float, rng: np.random.Generator,
                train_cams: Cameras, order: np.ndarray, anchors: np.ndarray,
                jit_t: np.ndarray, jit_R: np.ndarray):
    """Centres ``[T, L, 3]``, rotations ``[T, L, 3, 3]`` (world_from_cam) and focal scale
    ``[T, L]`` of the T trajectories of one mode."""
    T = a_pos.shape[0]
    t01 = (np.arange(L) + 1.0) / L  # linear modes: never exactly the anchor
    fwd = a_R[:, :, 2]
    fscale = np.ones((T, L))
    if mode == "orbit":
        s = rng.uniform(*cfg.orbit_radius_scale, size=T)
        arc = np.radians(rng.uniform(*cfg.orbit_arc_deg, size=T)) * rng.choice([-1.0, 1.0], T)
        off = s[:, None] * _safe_offset(a_pos, p, fwd, scale)
        theta = arc[:, None] * (np.arange(L) / (L - 1))[None]
        Rot = axis_angle_rotmat(up, theta)  # [T, L, 3, 3]
        c = p[:, None] + np.einsum("tlij,tj->tli", Rot, off)
        return c, _rot_look(c, p[:, None], up), fscale
    if mode == "spiral":
        off = _safe_offset(a_pos, p, fwd, scale)
        d = np.linalg.norm(off, axis=-1)
        Ra = _rot_look(a_pos, p, up)  # anchor looking at the target
        r = rng.uniform(*cfg.spiral_radius_scale, size=T) * d
        turns = rng.uniform(*cfg.spiral_turns, size=T)
        theta = 2 * np.pi * turns[:, None] * (np.arange(L) / L)[None]
        local = np.stack([np.cos(theta), -np.sin(theta), -np.sin(theta * cfg.spiral_zrate)], -1)
        c = a_pos[:, None] + r[:, None, None] * np.einsum("tij,tlj->tli", Ra, local)
        return c, _rot_look(c, p[:, None], up), fscale
    if mode == "lemniscate":
        off = _safe_offset(a_pos, p, fwd, scale)
        A = np.radians(rng.uniform(*cfg.lemniscate_deg, size=T))
        t = 2 * np.pi * np.arange(L) / L
        az = 0.5 * A[:, None] * np.sin(t)[None]
        el = 0.25 * A[:, None] * np.sin(2 * t)[None]
        h = np.cross(up, off)
        hn = np.linalg.norm(h, axis=-1, keepdims=True)
        h = np.where(hn > 1e-9, h / np.maximum(hn, 1e-12), a_R[:, :, 0])
        Rel = axis_angle_rotmat(h[:, None], el)
        Raz = axis_angle_rotmat(up, az)
        c = p[:, None] + np.einsum("tlij,tljk,tk->tli", Raz, Rel, off)
        return c, _rot_look(c, p[:, None], up), fscale
    if mode in ("dolly_in", "dolly_out"):
        factor = cfg.dolly_in_factor if mode == "dolly_in" else cfg.dolly_out_factor
        off = _safe_offset(a_pos, p, fwd, scale)
        rho = 1.0 + (factor - 1.0) * t01
        c = p[:, None] + rho[None, :, None] * off[:, None]
        return c, _rot_look(c, p[:, None], up), np.broadcast_to(rho, (T, L)).copy()
    if mode.startswith("move_"):
        right = a_R[:, :, 0] - np.outer(a_R[:, :, 0] @ up, up)
        rn = np.linalg.norm(right, axis=-1, keepdims=True)
        right = np.where(rn > 1e-6, right / np.maximum(rn, 1e-12), a_R[:, :, 0])
        direction = {"move_up": np.tile(up, (T, 1)), "move_down": np.tile(-up, (T, 1)),
                     "move_right": right, "move_left": -right}[mode]
        D = rng.uniform(*cfg.move_distance, size=T) * scale
        c = a_pos[:, None] + (D[:, None] * t01[None])[..., None] * direction[:, None]
        return c, np.repeat(a_R[:, None], L, axis=1), fscale
    if mode == "interpolation":
        c, R = _interpolation(train_cams, order, anchors, L, cfg.interp_span, jit_t, jit_R)
        return c, R, fscale
    raise ValueError(f"unknown trajectory mode {mode!r}")


def _interpolation(train_cams: Cameras, order: np.ndarray, anchors: np.ndarray, L: int,
                   span: float, jit_t: np.ndarray, jit_R: np.ndarray):
    """Spline through training centres in capture order around each anchor, plus the
    anchor's jitter applied rigidly to the whole segment."""
    P = train_cams.centers[order]
    Q = rotmat_to_quat_wxyz(train_cams.world_from_cam[order, :3, :3])
    n = len(order)
    rank = np.empty(len(train_cams), np.int64)
    rank[order] = np.arange(n)
    if n >= 3:
        from scipy.interpolate import CubicSpline

        spline = CubicSpline(np.arange(n), P, bc_type="natural")
    T = len(anchors)
    u = span * (2.0 * (np.arange(L) + 0.5) / L - 1.0)  # symmetric, avoids the knots
    cs, Rs = [], []
    for k in range(T):
        pos = float(rank[anchors[k]])
        if n - 1 >= 2 * span:
            pos = min(max(pos, span), n - 1 - span)
            tau = pos + u
        else:
            tau = (n - 1) * (u - u.min()) / max(u.max() - u.min(), 1e-12)
        if n >= 3:
            c = spline(tau)
        elif n == 2:
            c = P[0] + tau[:, None] * (P[1] - P[0])
        else:
            c = np.repeat(P[:1], L, axis=0)
        i0 = np.clip(np.floor(tau).astype(np.int64), 0, n - 1)
        i1 = np.minimum(i0 + 1, n - 1)
        q = slerp_wxyz(Q[i0], Q[i1], tau - i0)
        cs.append(c + jit_t[k])
        Rs.append(jit_R[k] @ quat_wxyz_to_rotmat(q))
    return np.stack(cs), np.stack(Rs)


# ---------------------------------------------------------------------- main entry
def generate_candidates(train_cams: Cameras, grid: CertaintyGrid, cfg: CandidateConfig,
                        seed: int, capture_order: np.ndarray | None = None) -> CandidateSet:
    """Stage 3: candidate cameras of every configured mode.

    Args:
        train_cams: T training cameras.
        grid: the certainty grid (box, look-at pool).
        cfg: candidate settings; N = len(modes) * n_traj * frames_per_traj cameras.
        seed: same seed, same cameras.
        capture_order: ``[T]`` indices of ``train_cams`` in capture order (interpolation);
            default ``0 .. T-1``.
    Returns:
        the :class:`CandidateSet`, ordered mode by mode (cfg order), trajectory by trajectory.
    """
    Tn = len(train_cams)
    order = np.arange(Tn) if capture_order is None else np.asarray(capture_order, np.int64)
    up = world_up(train_cams)
    scale = scene_scale(train_cams, grid, cfg.scale_unit)
    pool, fallback = lookat_pool(grid, cfg.lookat_central_fraction, cfg.lookat_quantile)
    if cfg.lookat_source == "box_center":
        pool, fallback = np.zeros((0, 3), np.int64), "lookat_source = box_center"
    L, n_traj = cfg.frames_per_traj, cfg.n_traj
    W2C = train_cams.world_from_cam
    parts_c, parts_R, parts_f, trajs, frames, anchors_all, looks = [], [], [], [], [], [], []
    modes: list[str] = []
    for m in cfg.modes:
        mid = TRAJECTORY_MODES.index(m)
        rng = np.random.default_rng([int(seed), 1000 + mid])
        anchors = select_anchors(train_cams.centers, n_traj, cfg.anchor_method, rng)
        sig = rng.uniform(*cfg.anchor_sigma, size=n_traj) * scale
        jit_t = rng.normal(size=(n_traj, 3)) * sig[:, None]
        jit_R = random_rotations(n_traj, cfg.anchor_rot_deg, rng)
        a_pos = W2C[anchors, :3, 3] + jit_t
        a_R = jit_R @ W2C[anchors, :3, :3]
        if m in OBJECT_CENTRIC_MODES:
            p = _sample_lookat(grid, pool, n_traj, rng)
        else:
            p = np.full((n_traj, 3), np.nan)
        c, R, fs = _mode_paths(m, a_pos, a_R, p, L, cfg, up, scale, rng, train_cams, order,
                               anchors, jit_t, jit_R)
        parts_c.append(c.reshape(-1, 3))
        parts_R.append(R.reshape(-1, 3, 3))
        parts_f.append(fs.reshape(-1))
        modes += [m] * (n_traj * L)
        trajs.append(np.repeat(mid * n_traj + np.arange(n_traj), L))
        frames.append(np.tile(np.arange(L), n_traj))
        anchors_all.append(np.repeat(anchors, L))
        looks.append(np.repeat(p, L, axis=0))
    centers = np.concatenate(parts_c)
    Rm = np.concatenate(parts_R)
    fscale = np.concatenate(parts_f)
    anchor_idx = np.concatenate(anchors_all)
    N = centers.shape[0]
    # random perturbation of a random subset
    rng = np.random.default_rng([int(seed), 2000])
    n_pert = int(round(cfg.perturb_fraction * N))
    perturbed = np.zeros(N, bool)
    if n_pert:
        sel = rng.choice(N, size=n_pert, replace=False)
        perturbed[sel] = True
        sig = rng.uniform(*cfg.perturb_sigma, size=n_pert) * scale
        centers[sel] += rng.normal(size=(n_pert, 3)) * sig[:, None]
        Rm[sel] = random_rotations(n_pert, cfg.perturb_rot_deg, rng) @ Rm[sel]
    # re-orthonormalise (products of rotations drift by ~1e-16)
    U, _, Vt = np.linalg.svd(Rm)
    Rm = U @ Vt
    cams = Cameras(make_pose(Rm, centers), train_cams.fx[anchor_idx] * fscale,
                   train_cams.fy[anchor_idx] * fscale, train_cams.cx[anchor_idx],
                   train_cams.cy[anchor_idx], train_cams.width[anchor_idx],
                   train_cams.height[anchor_idx])
    return CandidateSet(cams, np.array(modes), np.concatenate(trajs), np.concatenate(frames),
                        anchor_idx, np.concatenate(looks), perturbed, scale, up, len(pool),
                        fallback)
