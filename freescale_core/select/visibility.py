"""Voxel visibility M_ik (METHOD.md stage 5).

Only voxels with C > 0 matter for Eq. 3, so visibility is computed on the sparse list of the
K non-empty voxels (K << R^3), one bit per (view, voxel), packed 8 per byte (np.packbits
order: voxel ``8b + j`` is bit ``128 >> j`` of byte ``b``). Two rules:

* ``frustum`` (the paper): voxel centre X projects inside the image,
  ``0 <= u < W, 0 <= v < H``, with camera depth ``z > near``;
* ``occlusion`` (ours): additionally the voxel is not hidden behind occupied voxels. Per
  camera the occupied voxels are splatted into a low-resolution z-buffer (each voxel covers
  a square of radius = its projected half-diagonal, capped), and a voxel is visible when its
  depth is at most the z-buffer depth at its pixel plus a margin of a few voxel edges.

The kernels are numba-parallel over views; the score f_i = sum_k C_k M_ik (Eq. 3 node score)
is accumulated in float64 in the same pass.

Cell summaries (for exact pruning in NMS, see ``nms.py``): the voxel list is sorted by coarse
cell (``cells_per_axis`` cells per axis); per view and cell the kernel also records the
visible certainty Q_ic = sum_{k in c} C_k M_ik and a state: 0 = no voxel of the cell visible,
1 = some, 2 = all. With F = [state == 2] and Qp = Q [state == 1],

    L_ij = F_i . Qp_j + Q_i . F_j  <=  I_ij  <=  L_ij + sqrt(Qp_i) . sqrt(Qp_j) = U_ij

(cells fully seen by one view contribute exactly; only cells partial in both are bounded),
two small GEMMs over cells instead of voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from schemas.select import VisibilityConfig

from freescale_core.geometry.cameras import Cameras
from freescale_core.select.certainty import CertaintyGrid

__all__ = ["Visibility", "compute_visibility", "cell_order", "unpack_rows"]


@dataclass
class Visibility:
    """Binary visibility of the K non-empty voxels in N views.

    Attributes:
        bits: ``[N, ceil(K / 8)]`` uint8 packed M (np.packbits bit order).
        weights: ``[K]`` float64 certainty C_k of the listed voxels.
        score: ``[N]`` float64 node score f_i = sum_k C_k M_ik.
        voxel_idx: ``[K, 3]`` int64 voxel indices (ix, iy, iz), sorted by cell.
        mode: "frustum" or "occlusion".
        cell_ptr: ``[n_cells + 1]`` voxels of cell c are ``cell_ptr[c] : cell_ptr[c + 1]``.
        cell_q: ``[N, n_cells]`` float32 visible certainty per cell, in units of c0.
        cell_state: ``[N, n_cells]`` uint8: 0 none, 1 partly, 2 fully visible.
    """

    bits: np.ndarray
    weights: np.ndarray
    score: np.ndarray
    voxel_idx: np.ndarray
    mode: str
    cell_ptr: np.ndarray = None
    cell_q: np.ndarray = None
    cell_state: np.ndarray = None

    def __post_init__(self) -> None:
        n = self.bits.shape[0]
        if self.cell_ptr is None:
            self.cell_ptr = np.zeros(1, np.int64)
            self.cell_q = np.zeros((n, 0), np.float32)
            self.cell_state = np.zeros((n, 0), np.uint8)

    @classmethod
    def from_dense(cls, M: np.ndarray, weights: np.ndarray, cell_ptr: np.ndarray | None = None,
                   voxel_idx: np.ndarray | None = None, mode: str = "given") -> "Visibility":
        """Build from a dense ``M [N, K]`` (bool) and ``weights [K]`` (voxels already in cell
        order when ``cell_ptr [n_cells + 1]`` is given). For tests and external visibility."""
        M = np.asarray(M, dtype=bool)
        w = np.asarray(weights, dtype=np.float64)
        N, K = M.shape
        score = M.astype(np.float64) @ w
        vi = np.zeros((K, 3), np.int64) if voxel_idx is None else np.asarray(voxel_idx)
        if cell_ptr is None:
            return cls(np.packbits(M, axis=1), w, score, vi, mode)
        cell_ptr = np.asarray(cell_ptr, dtype=np.int64)
        c0 = float(w.mean()) if K and w.mean() > 0 else 1.0
        nc = len(cell_ptr) - 1
        q = np.zeros((N, nc))
        st = np.zeros((N, nc), np.uint8)
        for c in range(nc):
            a, b = cell_ptr[c], cell_ptr[c + 1]
            cnt = M[:, a:b].sum(axis=1)
            q[:, c] = M[:, a:b].astype(np.float64) @ w[a:b]
            st[:, c] = np.where(cnt == 0, 0, np.where(cnt == b - a, 2, 1))
        return cls(np.packbits(M, axis=1), w, score, vi, mode, cell_ptr,
                   (q / c0).astype(np.float32), st)

    @property
    def n_cells(self) -> int:
        """Number of coarse cells (0 = no bounds: a single segment is not a cell grid)."""
        return int(self.cell_ptr.shape[0] - 1) if self.cell_ptr.shape[0] > 2 else 0

    @property
    def n_views(self) -> int:
        return int(self.bits.shape[0])

    @property
    def n_voxels(self) -> int:
        return int(self.weights.shape[0])

    @property
    def norm(self) -> float:
        """Weight normaliser c0 (mean C): GEMMs run on C / c0, which is O(1)."""
        c0 = float(self.weights.mean()) if self.weights.size else 0.0
        return c0 if c0 > 0 else 1.0

    def dense(self, rows: np.ndarray | None = None) -> np.ndarray:
        """``[n, K]`` bool M for views ``rows`` (all by default)."""
        b = self.bits if rows is None else self.bits[np.asarray(rows)]
        return np.unpackbits(b, axis=1, count=self.n_voxels).astype(bool)

    def weighted_rows(self, rows: np.ndarray, dtype=np.float32, k0: int = 0,
                      k1: int | None = None) -> np.ndarray:
        """``[n, k1 - k0]`` rows ``M_ik * sqrt(C_k / c0)`` for voxels ``k0 <= k < k1`` (all
        by default), so that ``rows_a @ rows_b.T = I / c0``."""
        rows = np.ascontiguousarray(rows, dtype=np.int64)
        k1 = self.n_voxels if k1 is None else min(k1, self.n_voxels)
        sw = np.sqrt(self.weights / self.norm).astype(dtype)
        out = np.empty((rows.shape[0], max(0, k1 - k0)), dtype=dtype)
        unpack_rows(self.bits, rows, sw, int(k0), out)
        return out

    def bound_rows(self, rows: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
        """Cell rows for the bounds: ``side="left"`` gives ``([F, Q], sqrt(Qp))``,
        ``side="right"`` gives ``([Qp, F], sqrt(Qp))`` (each ``[n, 2 n_cells]`` /
        ``[n, n_cells]`` float32), so that ``L = left0 @ right0.T`` and
        ``U = L + left1 @ right1.T`` (in units of c0)."""
        rows = np.asarray(rows, dtype=np.int64)
        st = self.cell_state[rows]
        q = self.cell_q[rows]
        full = (st == 2).astype(np.float32)
        qp = np.where(st == 1, q, np.float32(0))
        a = np.concatenate([full, q] if side == "left" else [qp, full], axis=1)
        return a, np.sqrt(qp)

    def subset(self, rows: np.ndarray) -> "Visibility":
        rows = np.asarray(rows)
        return Visibility(self.bits[rows], self.weights, self.score[rows], self.voxel_idx,
                          self.mode, self.cell_ptr, self.cell_q[rows], self.cell_state[rows])


# ---------------------------------------------------------------------- kernels
# Branch-free inner loops (numba + LLVM vectorise them); projection without division:
# with P = K [R | t] and (px, py, z) = P X, the pixel (px / z, py / z) is inside the image
# iff z > near, 0 <= px < W z and 0 <= py < H z.
def _unpack_rows_py(bits, rows, sqrt_w, k0, out):  # pragma: no cover - compiled
    """out[r, k - k0] = sqrt_w[k] if bit k of view rows[r] is set else 0, k0 <= k < k0 + n."""
    n = out.shape[1]
    for r in nb.prange(rows.shape[0]):
        src = bits[rows[r]]
        o = out[r]
        for j in range(n):
            k = k0 + j
            o[j] = sqrt_w[k] * ((src[k >> 3] >> (7 - (k & 7))) & 1)


_unpack_parallel = nb.njit(parallel=True, cache=True, nogil=True, fastmath=True)(_unpack_rows_py)
_unpack_serial = nb.njit(parallel=False, cache=True, nogil=True, fastmath=True)(_unpack_rows_py)


def unpack_rows(bits, rows, sqrt_w, k0, out) -> None:
    """Unpack weighted rows (see ``_unpack_rows_py``); small jobs stay on the calling thread
    (waking a thread pool for a few rows costs more than it saves on a busy machine)."""
    (_unpack_parallel if out.size >= (1 << 23) else _unpack_serial)(bits, rows, sqrt_w, k0, out)


@nb.njit(inline="always")
def _pack(m, bits_row):  # pragma: no cover - compiled
    for b in range(bits_row.shape[0]):
        o = 8 * b
        bits_row[b] = ((m[o] << 7) | (m[o + 1] << 6) | (m[o + 2] << 5) | (m[o + 3] << 4)
                       | (m[o + 4] << 3) | (m[o + 5] << 2) | (m[o + 6] << 1) | m[o + 7])


@nb.njit(inline="always")
def _cells(m, w, cell_ptr, cell_mass, inv_c0, q_row, st_row):  # pragma: no cover - compiled
    """Per-cell state and visible certainty (x inv_c0) of one view from its mask ``m``;
    returns f (raw units)."""
    acc = 0.0
    for c in range(cell_ptr.shape[0] - 1):
        a, b = cell_ptr[c], cell_ptr[c + 1]
        cnt = 0
        for k in range(a, b):
            cnt += m[k]
        if cnt == 0:
            q = 0.0
            st_row[c] = 0
        elif cnt == b - a:
            q = cell_mass[c]
            st_row[c] = 2
        else:
            q = 0.0
            for k in range(a, b):
                q += w[k] * m[k]
            st_row[c] = 1
        q_row[c] = q * inv_c0
        acc += q
    return acc


@nb.njit(parallel=True, cache=True, nogil=True, fastmath=True)
def _frustum_kernel(P, near, W, H, X, Y, Z, w, cell_ptr, cell_mass, inv_c0, bits, score, cell_q,
                    cell_state):  # pragma: no cover - compiled
    N = P.shape[0]
    K = X.shape[0]
    nbytes = bits.shape[1]
    for i in nb.prange(N):
        m = np.zeros(nbytes * 8, np.uint8)
        a0, a1, a2, a3 = P[i, 0, 0], P[i, 0, 1], P[i, 0, 2], P[i, 0, 3]
        b0, b1, b2, b3 = P[i, 1, 0], P[i, 1, 1], P[i, 1, 2], P[i, 1, 3]
        c0, c1, c2, c3 = P[i, 2, 0], P[i, 2, 1], P[i, 2, 2], P[i, 2, 3]
        Wi, Hi = W[i], H[i]
        for k in range(K):
            x, y, z = X[k], Y[k], Z[k]
            zc = c0 * x + c1 * y + c2 * z + c3
            px = a0 * x + a1 * y + a2 * z + a3
            py = b0 * x + b1 * y + b2 * z + b3
            m[k] = (zc > near) & (px >= 0.0) & (px < Wi * zc) & (py >= 0.0) & (py < Hi * zc)
        _pack(m, bits[i])
        score[i] = _cells(m, w, cell_ptr, cell_mass, inv_c0, cell_q[i], cell_state[i])


@nb.njit(parallel=True, cache=True, nogil=True, fastmath=True)
def _occlusion_kernel(P, near, W, H, X, Y, Z, w, cell_ptr, cell_mass, inv_c0, fx, occ,
                      half_diag, zw, margin, rmax, bits, score, cell_q, cell_state):
    N = P.shape[0]
    K = X.shape[0]
    nbytes = bits.shape[1]
    for i in nb.prange(N):
        m = np.zeros(nbytes * 8, np.uint8)
        a0, a1, a2, a3 = P[i, 0, 0], P[i, 0, 1], P[i, 0, 2], P[i, 0, 3]
        b0, b1, b2, b3 = P[i, 1, 0], P[i, 1, 1], P[i, 1, 2], P[i, 1, 3]
        c0, c1, c2, c3 = P[i, 2, 0], P[i, 2, 1], P[i, 2, 2], P[i, 2, 3]
        Wi, Hi = W[i], H[i]
        zh = max(1, int(round(zw * Hi / Wi)))
        sx = zw / Wi
        sy = zh / Hi
        fpix = fx[i]
        zbuf = np.full((zh, zw), np.inf)
        # pass 1: splat occupied voxels (radius = projected half-diagonal, in z-buffer px)
        for k in range(K):
            if not occ[k]:
                continue
            x, y, z = X[k], Y[k], Z[k]
            zc = c0 * x + c1 * y + c2 * z + c3
            if zc <= near:
                continue
            u = (a0 * x + a1 * y + a2 * z + a3) / zc * sx
            v = (b0 * x + b1 * y + b2 * z + b3) / zc * sy
            rad = min(rmax, int(half_diag * fpix * sx / zc))
            pu = int(np.floor(u))
            pv = int(np.floor(v))
            if pu + rad < 0 or pu - rad >= zw or pv + rad < 0 or pv - rad >= zh:
                continue
            for qv in range(max(0, pv - rad), min(zh, pv + rad + 1)):
                for qu in range(max(0, pu - rad), min(zw, pu + rad + 1)):
                    if zc < zbuf[qv, qu]:
                        zbuf[qv, qu] = zc
        # pass 2: frustum test, then depth test against the z-buffer
        for k in range(K):
            x, y, z = X[k], Y[k], Z[k]
            zc = c0 * x + c1 * y + c2 * z + c3
            px = a0 * x + a1 * y + a2 * z + a3
            py = b0 * x + b1 * y + b2 * z + b3
            if (zc > near) & (px >= 0.0) & (px < Wi * zc) & (py >= 0.0) & (py < Hi * zc):
                qu = min(zw - 1, int(px / zc * sx))
                qv = min(zh - 1, int(py / zc * sy))
                if zc <= zbuf[qv, qu] + margin:
                    m[k] = 1
        _pack(m, bits[i])
        score[i] = _cells(m, w, cell_ptr, cell_mass, inv_c0, cell_q[i], cell_state[i])


# ---------------------------------------------------------------------- entry point
def cell_order(voxel_idx: np.ndarray, R: int, cells_per_axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Sort voxels by coarse cell.

    Returns:
        ``(order [K], cell_ptr [n_cells + 1])``: voxel ``order[j]`` is the j-th in cell
        order; non-empty cells only. ``cells_per_axis = 0`` gives no cells.
    """
    K = voxel_idx.shape[0]
    if cells_per_axis <= 0 or K == 0:  # one segment holding every voxel (no bounds)
        return np.arange(K), np.array([0, K], np.int64)
    e = int(np.ceil(R / cells_per_axis))
    nb_ = int(np.ceil(R / e))
    c = voxel_idx // e
    cid = (c[:, 0] * nb_ + c[:, 1]) * nb_ + c[:, 2]
    order = np.argsort(cid, kind="stable")  # voxel_idx is in flat order already
    cs = cid[order]
    starts = np.flatnonzero(np.r_[True, cs[1:] != cs[:-1]])
    return order, np.r_[starts, K].astype(np.int64)


def compute_visibility(cams: Cameras, grid: CertaintyGrid, cfg: VisibilityConfig | None = None,
                       cells_per_axis: int = 16) -> Visibility:
    """Stage 5 visibility of every non-empty voxel in every view.

    Args:
        cams: N views (training then candidates, in graph node order).
        grid: certainty grid; voxels with C > 0 are listed.
        cfg: rule (frustum / occlusion) and its parameters.
        cells_per_axis: coarse cells for the NMS bounds (0 = none).
    Returns:
        :class:`Visibility` with packed M, weights C_k, scores f_i and cell summaries.
    """
    cfg = cfg or VisibilityConfig()
    idx, centers, w = grid.nonzero()
    order, cell_ptr = cell_order(idx, grid.R, cells_per_axis)
    idx, centers, w = idx[order], centers[order], w[order]
    K = centers.shape[0]
    N = len(cams)
    nc = cell_ptr.shape[0] - 1
    bits = np.zeros((N, (K + 7) // 8), np.uint8)
    score = np.zeros(N, np.float64)
    cell_q = np.zeros((N, nc), np.float32)
    cell_state = np.zeros((N, nc), np.uint8)
    if N == 0 or K == 0:
        return Visibility(bits, w, score, idx, cfg.mode, cell_ptr, cell_q,
                          cell_state)
    c0 = float(w.mean()) if w.mean() > 0 else 1.0  # = Visibility.norm
    # work relative to the box centre (smaller coordinates, same projections)
    o = 0.5 * (grid.bbox_min + grid.bbox_max)
    cfw = cams.cam_from_world
    t_local = cfw[:, :3, 3] + np.einsum("nij,j->ni", cfw[:, :3, :3], o)
    P = np.einsum("nij,njk->nik", cams.K, np.concatenate([cfw[:, :3, :3], t_local[..., None]], 2))
    X = centers - o
    args = (np.ascontiguousarray(P), float(cfg.near * grid.diagonal),
            cams.width.astype(np.float64), cams.height.astype(np.float64),
            *(np.ascontiguousarray(X[:, j]) for j in range(3)), w, cell_ptr,
            np.add.reduceat(w, cell_ptr[:-1]) if nc else np.zeros(0), 1.0 / c0)
    if cfg.mode == "frustum":
        _frustum_kernel(*args, bits, score, cell_q, cell_state)
    elif cfg.mode == "occlusion":
        from freescale_core.select.feasibility import occupancy_grid

        occ_grid, _ = occupancy_grid(grid, cfg.occluder_quantile)
        occ = occ_grid[idx[:, 0], idx[:, 1], idx[:, 2]]
        vs = grid.voxel_size
        half_diag = 0.5 * float(np.linalg.norm(vs))
        margin = cfg.depth_margin_voxels * float(vs.max())
        _occlusion_kernel(*args, cams.fx, occ, half_diag, int(cfg.zbuffer_width), margin,
                          int(cfg.max_splat_radius), bits, score, cell_q, cell_state)
    else:
        raise ValueError(f"unknown visibility mode {cfg.mode!r}")
    return Visibility(bits, w, score, idx, cfg.mode, cell_ptr, cell_q, cell_state)
