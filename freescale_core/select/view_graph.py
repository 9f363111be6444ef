"""View graph (METHOD.md stage 5, Eq. 3).

W_ik = C(v_k) M_ik; WIoU(i, j) = sum_k min(W_ik, W_jk) / sum_k max(W_ik, W_jk); node score
f_i = sum_k W_ik. With binary M, min(W_ik, W_jk) = C_k M_ik M_jk and max = C_k (M_ik + M_jk -
M_ik M_jk), so

    WIoU(i, j) = I_ij / (f_i + f_j - I_ij),   I = M diag(C) M^T,

one weighted Gram matrix. It is computed as GEMMs of rows ``M_ik sqrt(C_k / c0)`` (numpy BLAS,
float32 by default), never as a per-pair loop; 0/0 (two views that see no voxel) is 0.

Edges: among a node set (the kept views), each node keeps its top-k neighbours with
WIoU > threshold; an edge is stored once (src < dst) when either endpoint keeps it.

The ``pose_distance`` ablation (no certainty grid) replaces WIoU by the pose distance
``d(i, j) = |c_i - c_j| / s + angle(R_i, R_j) / rot_unit`` (s = median nearest-neighbour
spacing of the training centres, rot_unit = 10 deg by default); views closer than the
threshold (3.5) are "the same view".
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freescale_core.geometry.cameras import Cameras
from freescale_core.select.visibility import Visibility

__all__ = ["Edges", "wiou_from_inter", "wiou_block", "wiou_matrix",
           "wiou_definition",
           "edges_from_matrix", "camera_spacing", "pose_distance", "empty_edges"]


@dataclass
class Edges:
    """Undirected edge list over graph nodes (training-then-candidate numbering).

    Attributes:
        src, dst: ``[E]`` int64 node ids, src < dst.
        wiou: ``[E]`` float64 WIoU (NaN in the pose_distance ablation).
        distance: ``[E]`` float64 pose distance (NaN in WIoU mode).
    """

    src: np.ndarray
    dst: np.ndarray
    wiou: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return int(self.src.shape[0])


def empty_edges() -> Edges:
    z = np.zeros(0, np.int64)
    return Edges(z, z.copy(), np.zeros(0), np.zeros(0))


def wiou_from_inter(inter: np.ndarray, f_a: np.ndarray, f_b: np.ndarray) -> np.ndarray:
    """Eq. 3 from the Gram form: ``I / (f_a + f_b - I)`` with 0/0 = 0, clipped to [0, 1].

    Args:
        inter: ``[A, B]`` intersections I_ij (same units as f).
        f_a: ``[A]``, f_b: ``[B]`` node scores.
    """
    inter = np.asarray(inter, dtype=np.float64)
    den = f_a[:, None] + f_b[None, :] - inter
    out = np.divide(inter, den, out=np.zeros_like(inter), where=den > 0)
    return np.clip(out, 0.0, 1.0)


def wiou_block(vis: Visibility, rows_a: np.ndarray, rows_b: np.ndarray,
               dtype=np.float32) -> np.ndarray:
    """``[A, B]`` WIoU between views ``rows_a`` and ``rows_b`` (one GEMM)."""
    A = vis.weighted_rows(rows_a, dtype)
    B = A if np.array_equal(rows_a, rows_b) else vis.weighted_rows(rows_b, dtype)
    inter = A @ B.T
    fn = vis.score / vis.norm
    return wiou_from_inter(inter, fn[np.asarray(rows_a)], fn[np.asarray(rows_b)])


def wiou_matrix(vis: Visibility, nodes: np.ndarray, dtype=np.float32,
                chunk_voxels: int | None = None) -> np.ndarray:
    """``[n, n]`` symmetric WIoU among ``nodes`` (symmetric rank-K updates, summed over voxel
    chunks of ``chunk_voxels``; default: chunks whose unpacked rows take ~64 MB).

    The diagonal is 1 where f > 0 and 0 where the view sees no voxel.
    """
    nodes = np.asarray(nodes, dtype=np.int64)
    n, K = len(nodes), vis.n_voxels
    # accumulate over voxel chunks so the unpacked rows stay below ~64 MB
    chunk = chunk_voxels or max(1024, (64 << 20) // max(1, n * np.dtype(dtype).itemsize))
    inter = np.zeros((n, n), dtype=np.float64)
    for k0 in range(0, K, chunk):
        A = vis.weighted_rows(nodes, dtype, k0, k0 + chunk)
        inter += A @ A.T  # numpy dispatches X @ X.T to syrk
    inter = 0.5 * (inter + inter.T)
    fn = vis.score[nodes] / vis.norm
    W = wiou_from_inter(inter, fn, fn)
    d = np.where(fn > 0, 1.0, 0.0)
    np.fill_diagonal(W, d)
    return W


def wiou_definition(W: np.ndarray) -> np.ndarray:
    """Eq. 3 by its definition, sum min / sum max over voxels, for dense weights
    ``W [N, K]`` (W_ik = C_k M_ik, any non-negative weights). O(N^2 K): a reference for tests
    and small inputs only. 0/0 = 0."""
    W = np.asarray(W, dtype=np.float64)
    n = W.shape[0]
    out = np.zeros((n, n))
    for i in range(n):
        mn = np.minimum(W[i][None], W).sum(axis=1)
        mx = np.maximum(W[i][None], W).sum(axis=1)
        out[i] = np.divide(mn, mx, out=np.zeros(n), where=mx > 0)
    return out


def edges_from_matrix(S: np.ndarray, nodes: np.ndarray, threshold: float, top_k: int,
                      larger_is_closer: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Top-k edges per node from a dense pairwise matrix.

    Args:
        S: ``[n, n]`` symmetric WIoU (or distance when ``larger_is_closer`` is False).
        nodes: ``[n]`` node ids of the rows.
        threshold: keep pairs with S > threshold (WIoU) or S < threshold (distance).
        top_k: per node, the k best such pairs.
    Returns:
        ``(src, dst, value)`` with src < dst, each pair once.
    """
    n = S.shape[0]
    if n < 2:
        z = np.zeros(0, np.int64)
        return z, z.copy(), np.zeros(0)
    key = S.astype(np.float64).copy() if larger_is_closer else -S.astype(np.float64)
    ok = S > threshold if larger_is_closer else S < threshold
    key[~ok] = -np.inf
    np.fill_diagonal(key, -np.inf)
    k = min(top_k, n - 1)
    top = np.argpartition(-key, k - 1, axis=1)[:, :k]
    rows = np.repeat(np.arange(n), k)
    cols = top.reshape(-1)
    good = np.isfinite(key[rows, cols])
    rows, cols = rows[good], cols[good]
    a, b = np.minimum(rows, cols), np.maximum(rows, cols)
    pair = np.unique(a * n + b)
    a, b = pair // n, pair % n
    nodes = np.asarray(nodes, dtype=np.int64)
    u, v = nodes[a], nodes[b]
    src, dst = np.minimum(u, v), np.maximum(u, v)
    o = np.lexsort((dst, src))
    return src[o], dst[o], S[a, b].astype(np.float64)[o]


def camera_spacing(centers: np.ndarray, fallback: float) -> float:
    """Median nearest-neighbour distance of camera centres ``[N, 3]`` (``fallback`` if 0)."""
    c = np.asarray(centers, dtype=np.float64)
    if len(c) < 2:
        return float(fallback)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(c).query(c, k=2)
    s = float(np.median(d[:, 1]))
    return s if s > 0 else float(fallback)


def pose_distance(a: Cameras, b: Cameras, spacing: float, rot_unit_deg: float) -> np.ndarray:
    """``[A, B]`` pose distance ``|c_a - c_b| / spacing + angle(R_a, R_b) / rot_unit_deg``
    (angle in degrees): the ``pose_distance`` ablation's replacement for WIoU."""
    ca, cb = a.centers, b.centers
    dt = np.linalg.norm(ca[:, None] - cb[None], axis=-1) / spacing
    Ra, Rb = a.world_from_cam[:, :3, :3], b.world_from_cam[:, :3, :3]
    cos = (np.einsum("aij,bij->ab", Ra, Rb) - 1.0) / 2.0  # trace(Ra^T Rb)
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return dt + ang / rot_unit_deg
