"""More initial points: triangulate SIFT matches of the training views with the known cameras.

A scene whose SfM model is thin (buddha: 254 points for 13 views) starts its Gaussians from
few points. The cameras are known exactly (poses and pinhole intrinsics of the undistorted
images), so new points only need correspondences: :func:`triangulate_views` finds them and
triangulates them, using **only the views it is given** (the training views; a held-out view
is never read).

Route (OpenCV + numpy, not pycolmap's database pipeline): pycolmap 4.x can triangulate
matches against a fixed model (``pycolmap.triangulate_points``), but only through an on-disk
COLMAP database whose camera / image ids must match a ``Reconstruction`` built with rigs and
frames, images written to a folder at the working size, and COLMAP's multi-threaded RANSAC
and bundle adjustment in the loop. Here every step is a few numpy lines, in memory, and
deterministic by construction:

1. each view is resized (area) so its long side is at most ``max_long_side``; OpenCV SIFT
   (at most ``max_features`` per view), RootSIFT descriptors; keypoints in the project's
   pixel convention (pixel centres at ``i + 0.5``);
2. pairs: each view with its ``max_partners`` views of most similar viewing direction
   (at most ``max_pair_angle_deg`` apart);
3. matching *guided by the known geometry*: descriptor distances of candidates farther than
   ``max_epipolar_px`` from the epipolar line (fundamental matrix from the known poses, both
   directions) are discarded, then Lowe's ratio test among the remaining candidates and a
   mutual nearest-neighbour check;
4. tracks: connected components of the match graph; a track that holds two keypoints of one
   view is dropped;
5. linear multi-view triangulation (DLT on normalised image coordinates, in a world frame
   centred and scaled on the cameras); observations beyond ``max_reproj_px`` are dropped and
   the point re-triangulated once; a point is kept when it is seen by >= ``min_views`` views
   (2 by default), lies in front of every observing camera, reprojects within
   ``max_reproj_px`` in **every** observing view and its widest pair of observing rays is at
   least ``min_angle_deg`` apart;
6. colour: mean of the observing pixels.

Deterministic: no random sampling anywhere; OpenCV's thread count is set to 1 while it runs
(and restored), which also keeps it light on a shared CPU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from freescale_core.geometry.cameras import Cameras

__all__ = ["Triangulated", "triangulate_views", "merge_points"]


@dataclass
class Triangulated:
    """Points triangulated from a scene's views.

    Attributes:
        xyz: ``[P, 3]`` float64 world points. rgb: ``[P, 3]`` uint8 colours.
        track_len: ``[P]`` number of observing views.
        max_reproj_px: ``[P]`` largest reprojection error over the observing views (pixels
            at the working resolution).
        angle_deg: ``[P]`` widest angle between two observing rays (degrees).
        obs_point, obs_view, obs_uv: the observations kept, flattened: point index ``[M]``,
            scene camera index ``[M]``, pixel ``[M, 2]`` at the working resolution.
        scale: working resolution relative to the scene's images (``Cameras.scaled``).
        view_ids: the scene camera indices used (read), in the order given.
        stats: counts and seconds (``n_points``, ``seconds``, ``n_features``, ``n_pairs``,
            ``n_matches``, ``n_tracks``, rejections, ``median_reproj_px``).
    """

    xyz: np.ndarray
    rgb: np.ndarray
    track_len: np.ndarray
    max_reproj_px: np.ndarray
    angle_deg: np.ndarray
    obs_point: np.ndarray
    obs_view: np.ndarray
    obs_uv: np.ndarray
    scale: float
    view_ids: np.ndarray
    stats: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.xyz)


# --------------------------------------------------------------------------- features
def _features(img: np.ndarray, sift) -> tuple[np.ndarray, np.ndarray]:
    """``(uv [K, 2] float64 in pixel-centre-at-0.5 convention, RootSIFT [K, 128] float32)``."""
    import cv2

    gray = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    kps, desc = sift.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32)
    uv = np.array([k.pt for k in kps], np.float64) + 0.5
    d = desc.astype(np.float32)
    d /= np.maximum(d.sum(axis=1, keepdims=True), 1e-12)  # RootSIFT: L1, sqrt -> unit L2
    d = np.sqrt(d)
    # identical keypoints at one location (several orientations) make the ratio test fail:
    # keep the first of each exact (u, v) position
    _, first = np.unique(np.round(uv, 3), axis=0, return_index=True)
    first = np.sort(first)
    return uv[first], d[first]


def _pairs(cams: Cameras, max_partners: int, max_angle_deg: float) -> list[tuple[int, int]]:
    """Each view with its ``max_partners`` views of closest viewing direction (``i < j``)."""
    f = cams.forward / np.linalg.norm(cams.forward, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(f @ f.T, -1.0, 1.0)))
    n = len(cams)
    out = set()
    for i in range(n):
        order = np.argsort(ang[i], kind="stable")
        k = 0
        for j in order:
            if j == i or ang[i, j] > max_angle_deg:
                continue
            out.add((min(i, int(j)), max(i, int(j))))
            k += 1
            if k >= max_partners:
                break
    return sorted(out)


def _fundamental(cams: Cameras, i: int, j: int) -> np.ndarray:
    """``F`` with ``x_j^T F x_i = 0`` for pixels of views ``i`` and ``j`` (homogeneous)."""
    T = cams.cam_from_world[j] @ cams.world_from_cam[i]
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    K = cams.K
    return np.linalg.inv(K[j]).T @ tx @ R @ np.linalg.inv(K[i])


def _match(uv_i, d_i, uv_j, d_j, F, max_epi_px: float, ratio: float) -> np.ndarray:
    """Guided matches ``[M, 2]`` (row in i, row in j)."""
    if len(uv_i) < 2 or len(uv_j) < 2:
        return np.zeros((0, 2), np.int64)
    hi = np.concatenate([uv_i, np.ones((len(uv_i), 1))], 1)
    hj = np.concatenate([uv_j, np.ones((len(uv_j), 1))], 1)
    li = hi @ F.T            # epipolar lines in j of the points of i  [Ni, 3]
    lj = hj @ F              # epipolar lines in i of the points of j  [Nj, 3]
    alg = np.abs(li @ hj.T)  # [Ni, Nj] |x_j^T F x_i|
    ok = ((alg <= max_epi_px * np.linalg.norm(li[:, :2], axis=1)[:, None])
          & (alg <= max_epi_px * np.linalg.norm(lj[:, :2], axis=1)[None, :]))
    full = np.sqrt(np.maximum(2.0 - 2.0 * (d_i @ d_j.T), 0.0))    # [Ni, Nj] RootSIFT distance
    dist = np.where(ok, full, np.float32(np.inf))
    best_j = np.argmin(dist, axis=1)                               # [Ni] among the candidates
    rows = np.arange(len(uv_i))
    d1 = dist[rows, best_j]
    # Lowe's ratio against the nearest *other* descriptor anywhere in j, on or off the line:
    # a descriptor with a near twin elsewhere (tiled or repeated texture) is ambiguous even if
    # only one twin lies on the epipolar line
    two = np.partition(full, 1, axis=1)[:, :2]                     # [Ni, 2] anywhere in j
    d2 = np.where(np.argmin(full, axis=1) == best_j, two[:, 1], two[:, 0])
    good = np.isfinite(d1) & (d1 < ratio * d2)
    best_i = np.argmin(dist, axis=0)                               # mutual check
    idx_i = np.nonzero(good)[0]
    idx_j = best_j[idx_i]
    mutual = best_i[idx_j] == idx_i
    return np.stack([idx_i[mutual], idx_j[mutual]], 1).astype(np.int64)


# --------------------------------------------------------------------------- triangulation
def _dlt(P: np.ndarray, xn: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Batched linear triangulation.

    Args:
        P: ``[T, L, 3, 4]`` camera matrices ``[R | t]`` (normalised coordinates).
        xn: ``[T, L, 2]`` normalised image coordinates. w: ``[T, L]`` 1 = use, 0 = ignore.
    Returns:
        ``[T, 4]`` homogeneous points.
    """
    r1 = xn[..., 0:1] * P[..., 2, :] - P[..., 0, :]
    r2 = xn[..., 1:2] * P[..., 2, :] - P[..., 1, :]
    A = np.concatenate([r1, r2], axis=1) * np.concatenate([w, w], axis=1)[..., None]
    _, _, vt = np.linalg.svd(A)
    return vt[:, -1, :]


def triangulate_views(scene, view_idx: Sequence[int] | np.ndarray, *, max_long_side: int = 512,
                      max_features: int = 4000, max_partners: int = 6,
                      max_pair_angle_deg: float = 60.0, max_epipolar_px: float = 1.5,
                      ratio: float = 0.85, max_reproj_px: float = 2.0, min_angle_deg: float = 2.0,
                      contrast_threshold: float = 0.005, min_views: int = 2) -> Triangulated:
    """Triangulate SIFT matches among the views ``view_idx`` of ``scene`` (see the module doc).

    Args:
        scene: anything with ``cameras`` (:class:`Cameras`, pinhole) and ``load_image(i)``;
            only ``load_image(i)`` for ``i`` in ``view_idx`` is called.
        view_idx: scene camera indices to use (the training views).
        max_long_side: images are downscaled (never upscaled) so the long side is at most this.
        max_features: SIFT features per view (strongest first).
        max_partners: views each view is matched with (closest viewing directions).
        max_pair_angle_deg: views farther apart in viewing direction are not matched.
        max_epipolar_px: largest distance of a match from its epipolar lines (pixels).
        ratio: Lowe's ratio among the epipolar candidates.
        max_reproj_px: largest reprojection error in every observing view (pixels).
        min_angle_deg: smallest widest angle between two observing rays.
        contrast_threshold: SIFT's contrast threshold (OpenCV's default 0.04; 0.005 finds
            ~1,300 instead of ~330 features per buddha view at 512 px).
        min_views: a point is kept when at least this many views observe it (after the
            reprojection filter). Two views cannot check a match that lies on its epipolar
            line: on a repeating or noisy texture such a wrong match triangulates cleanly at a
            wrong depth, often in front of the surface (a floater). A third view checks it.
    Returns:
        :class:`Triangulated` (possibly empty).
    """
    import cv2
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    t0, c0_cpu = time.perf_counter(), time.process_time()
    ids = np.asarray(view_idx, np.int64)
    native = scene.cameras.subset(ids)
    long_side = float(max(native.width.max(), native.height.max())) if len(ids) else 1.0
    scale = min(1.0, max_long_side / long_side)
    cams = native.scaled(scale)
    n = len(ids)
    stats: dict = {"n_views": n, "scale": scale, "max_long_side": max_long_side}

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=contrast_threshold)
        images, uvs, descs = [], [], []
        for k, i in enumerate(ids):
            img = scene.load_image(int(i))
            w, h = int(cams.width[k]), int(cams.height[k])
            if img.shape[1] != w or img.shape[0] != h:
                img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            uv, d = _features(img, sift)
            images.append(img)
            uvs.append(uv)
            descs.append(d)
    finally:
        cv2.setNumThreads(threads)
    t_feat = time.perf_counter() - t0
    stats["n_features"] = [len(u) for u in uvs]

    # ---- guided matching over the view pairs
    pairs = _pairs(cams, max_partners, max_pair_angle_deg) if n >= 2 else []
    offset = np.concatenate([[0], np.cumsum([len(u) for u in uvs])]).astype(np.int64)
    ea, eb = [], []
    for i, j in pairs:
        m = _match(uvs[i], descs[i], uvs[j], descs[j], _fundamental(cams, i, j),
                   max_epipolar_px, ratio)
        ea.append(offset[i] + m[:, 0])
        eb.append(offset[j] + m[:, 1])
    stats["n_pairs"] = len(pairs)
    n_nodes = int(offset[-1])
    a = np.concatenate(ea) if ea else np.zeros(0, np.int64)
    b = np.concatenate(eb) if eb else np.zeros(0, np.int64)
    stats["n_matches"] = int(len(a))
    t_match = time.perf_counter() - t0 - t_feat

    empty = Triangulated(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64),
                         np.zeros(0), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.int64),
                         np.zeros((0, 2)), scale, ids, stats)
    if len(a) == 0:
        stats.update(n_tracks=0, n_points=0, seconds=time.perf_counter() - t0)
        return empty

    # ---- tracks: connected components of the match graph
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_nodes, n_nodes))
    _, label = connected_components(g, directed=False)
    node_view = np.repeat(np.arange(n), np.diff(offset))
    node_kp = np.arange(n_nodes) - offset[node_view]
    in_edge = np.zeros(n_nodes, bool)
    in_edge[a] = in_edge[b] = True
    nodes = np.nonzero(in_edge)[0]
    order = np.lexsort((node_view[nodes], label[nodes]))
    nodes = nodes[order]
    lab = label[nodes]
    starts = np.concatenate([[0], np.nonzero(np.diff(lab))[0] + 1])
    lens = np.diff(np.concatenate([starts, [len(nodes)]]))
    track_of = np.repeat(np.arange(len(starts)), lens)
    # a view twice in one track: ambiguous, drop the track
    dup = np.zeros(len(starts), bool)
    same = (np.diff(node_view[nodes]) == 0) & (np.diff(lab) == 0)
    dup[track_of[1:][same]] = True
    keep_t = (~dup) & (lens >= 2)
    stats["n_tracks"] = int(len(starts))
    stats["rejected_conflicting_tracks"] = int(dup.sum())
    keep_nodes = keep_t[track_of]
    nodes, track_of = nodes[keep_nodes], track_of[keep_nodes]
    _, track_of = np.unique(track_of, return_inverse=True)
    T = int(track_of.max()) + 1 if len(track_of) else 0
    if T == 0:
        stats.update(n_points=0, seconds=time.perf_counter() - t0)
        return empty
    lens = np.bincount(track_of, minlength=T)
    L = int(lens.max())
    slot = np.arange(len(nodes)) - np.concatenate([[0], np.cumsum(lens)[:-1]])[track_of]
    views = np.zeros((T, L), np.int64)
    uv = np.zeros((T, L, 2))
    w = np.zeros((T, L))
    views[track_of, slot] = node_view[nodes]
    uv[track_of, slot] = np.concatenate(uvs)[nodes]
    w[track_of, slot] = 1.0
    kp = np.zeros((T, L), np.int64)
    kp[track_of, slot] = node_kp[nodes]

    # ---- DLT in a frame centred and scaled on the cameras (conditioning)
    c0 = cams.centers.mean(0)
    s0 = max(float(np.max(np.linalg.norm(cams.centers - c0, axis=1))), 1e-9)
    cfw = cams.cam_from_world.copy()
    Pn = np.concatenate([cfw[:, :3, :3] * s0, (cfw[:, :3, :3] @ c0 + cfw[:, :3, 3])[:, :, None]],
                        axis=2)  # maps (X - c0) / s0 homogeneous to camera coordinates
    xn = np.stack([(uv[..., 0] - cams.cx[views]) / cams.fx[views],
                   (uv[..., 1] - cams.cy[views]) / cams.fy[views]], -1)
    P = Pn[views]

    def solve(wt):
        Xh = _dlt(P, xn, wt)
        hw = Xh[:, 3:4]
        Xn = Xh[:, :3] / np.where(np.abs(hw) < 1e-12, 1e-12, hw)
        Xw = Xn * s0 + c0
        Xc = np.einsum("tlij,tj->tli", cfw[views][..., :3, :3], Xw) + cfw[views][..., :3, 3]
        z = Xc[..., 2]
        zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
        pu = cams.fx[views] * Xc[..., 0] / zs + cams.cx[views]
        pv = cams.fy[views] * Xc[..., 1] / zs + cams.cy[views]
        err = np.hypot(pu - uv[..., 0], pv - uv[..., 1])
        return Xw, z, err

    Xw, z, err = solve(w)
    w2 = w * ((err <= max_reproj_px) & (z > 0))
    redo = (w2.sum(1) >= 2) & (w2.sum(1) < w.sum(1))
    if redo.any():
        Xr, zr, er = solve(np.where(redo[:, None], w2, w))
        Xw[redo], z[redo], err[redo] = Xr[redo], zr[redo], er[redo]
        w = np.where(redo[:, None], w2, w)
    used = w > 0
    n_obs = used.sum(1)
    ok_views = n_obs >= max(2, int(min_views))
    ok_depth = np.all(~used | (z > 0), axis=1)
    emax = np.where(used, err, 0.0).max(1)
    ok_reproj = emax <= max_reproj_px
    # widest angle between two observing rays
    rays = Xw[:, None, :] - cams.centers[views]
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), 1e-12)
    cos = np.einsum("tai,tbi->tab", rays, rays)
    both = used[:, :, None] & used[:, None, :]
    min_cos = np.where(both, cos, 1.0).min((1, 2))
    ok_angle = min_cos <= np.cos(np.radians(min_angle_deg))
    finite = np.all(np.isfinite(Xw), axis=1)
    keep = ok_views & ok_depth & ok_reproj & ok_angle & finite
    stats.update(rejected_views=int((~ok_views).sum()),
                 rejected_depth=int((ok_views & ~ok_depth).sum()),
                 rejected_reproj=int((ok_views & ok_depth & ~ok_reproj).sum()),
                 rejected_angle=int((ok_views & ok_depth & ok_reproj & ~ok_angle).sum()))

    angle = np.degrees(np.arccos(np.clip(min_cos[keep], -1.0, 1.0)))
    Xw, used, uv, views, emax = Xw[keep], used[keep], uv[keep], views[keep], emax[keep]
    obs_t, obs_l = np.nonzero(used)
    obs_view_local = views[obs_t, obs_l]
    obs_uv = uv[obs_t, obs_l]
    # colour: mean of the observing pixels (nearest pixel at the working resolution)
    rgb_sum = np.zeros((len(Xw), 3))
    for k in range(n):
        m = obs_view_local == k
        if not m.any():
            continue
        img = images[k]
        px = np.clip(np.floor(obs_uv[m, 0]).astype(int), 0, img.shape[1] - 1)
        py = np.clip(np.floor(obs_uv[m, 1]).astype(int), 0, img.shape[0] - 1)
        np.add.at(rgb_sum, obs_t[m], img[py, px, :3].astype(np.float64))
    n_obs = used.sum(1)
    rgb = np.clip(np.rint(rgb_sum / np.maximum(n_obs, 1)[:, None]), 0, 255).astype(np.uint8)
    stats.update(n_points=int(len(Xw)),
                 median_reproj_px=float(np.median(emax)) if len(emax) else None,
                 median_track_len=float(np.median(n_obs)) if len(n_obs) else None,
                 seconds_features=t_feat, seconds_matching=t_match,
                 seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0_cpu)
    return Triangulated(Xw, rgb, n_obs.astype(np.int64), emax, angle, obs_t.astype(np.int64),
                        ids[obs_view_local], obs_uv, scale, ids, stats)


def merge_points(xyz: np.ndarray, rgb: np.ndarray, tri: Triangulated
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The given points followed by the triangulated ones."""
    return (np.concatenate([np.asarray(xyz, np.float64).reshape(-1, 3), tri.xyz]),
            np.concatenate([np.asarray(rgb, np.uint8).reshape(-1, 3), tri.rgb]))
