"""Reference-view selection for image rectification (METHOD.md stage 10).

Every kept free view is rectified with one *reference*: a training view whose photo shows the
same surfaces. Two rules, selectable in ``ReferenceConfig.rule``:

* ``"graph"`` (the paper: the first training neighbour within two hops, by WIoU).

  0. direct, at the final pose (``ReferenceConfig.overlap = "final_pose"``, default): the
     WIoU between the free view at its *final* pose (after pose rectification) and every
     training view, computed from the certainty grid and the visibility rule
     (:class:`TrainOverlap`, one row of the Gram product); the training view with the highest
     WIoU > 0 is the reference (``"wiou_direct"``). This is the direct neighbour of the
     complete view graph: the stored graph keeps only the top-k edges per node above a
     threshold, and its edges belong to the candidate's *original* pose. By default the WIoU
     carries a view-direction kernel (``ReferenceConfig.overlap_angle_deg``, ours; see
     :class:`TrainOverlap`): a shared voxel counts only as far as the two views see it from
     similar directions; ``overlap_angle_deg = None`` is Eq. 3 as is.
  1. direct, stored graph: among the training views joined to the free view's node by a stored
     edge, the one with the highest WIoU (``"graph_direct"``);
  2. two hops: otherwise, over every path ``v - u - t`` (``u`` any node, ``t`` a training view)
     the path with the highest score, ``WIoU(v,u) * WIoU(u,t)`` (default, ``"product"``: the
     chance that overlap survives both hops) or ``min(WIoU(v,u), WIoU(u,t))`` (``"min"``: the
     weakest link) (``"graph_2hop"``);
  3. otherwise (no training view within two hops, e.g. an isolated node) the pose rule is
     used and the choice is labelled ``"pose_fallback"``, so it is never silent.

  Step 0 runs when the caller supplies the overlap row (``run_freeviews``' ``overlap_fn``);
  steps 1-2 are used when it is absent (``overlap = "stored_graph"``, the earlier behaviour)
  or when the final pose shares no certain voxel with any training view.
  Ties go to the lowest training index. The graph is undirected: an edge listed as (a, b) or
  (b, a) is the same edge; duplicates keep their highest WIoU.
* ``"pose"`` (Difix3D-style nearest pose): smallest ``|c_v - c_t| / L + w_rot * angle(R_v,
  R_t)``, with the angle in radians and ``L`` the median distance of the training centres to
  their centroid, which makes the translation term scale-free (COLMAP units are arbitrary).
  With ``w_rot = 1`` (default), a 1-radian (57 deg) turn weighs as much as moving the camera by
  the typical camera-to-centroid distance. Difix3D publishes no weights; these are ours.

Node numbering (the selection core's): training views are nodes ``0 .. T-1``, candidate ``j``
is node ``T + j``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.freeview import ReferenceConfig

from freescale_core.geometry.cameras import Cameras, rotation_angle_deg
from freescale_core.errors import ShapeError

__all__ = ["ViewGraph", "ReferenceChoice", "TrainOverlap", "graph_reference", "pose_reference",
           "select_reference"]


@dataclass
class ViewGraph:
    """The view graph as an undirected adjacency (CSR) over training-then-candidate nodes.

    Attributes:
        n_train: T, the number of training nodes (nodes ``0 .. T-1``).
        n_nodes: total number of nodes.
        indptr: ``[n_nodes + 1]`` CSR row pointers.
        indices: ``[E2]`` neighbour node of each adjacency entry.
        weights: ``[E2]`` WIoU of each adjacency entry.
    """

    n_train: int
    n_nodes: int
    indptr: np.ndarray
    indices: np.ndarray
    weights: np.ndarray

    @classmethod
    def from_edges(cls, n_train: int, n_nodes: int, src: np.ndarray, dst: np.ndarray,
                   wiou: np.ndarray) -> "ViewGraph":
        """Build from an edge list (either direction, duplicates allowed, self-loops ignored).

        Args:
            n_train: T.
            n_nodes: T + number of candidates.
            src, dst: ``[E]`` node ids.
            wiou: ``[E]`` edge weights (WIoU in [0, 1]); edges with WIoU <= 0 are dropped.
        """
        src = np.asarray(src, dtype=np.int64).ravel()
        dst = np.asarray(dst, dtype=np.int64).ravel()
        w = np.asarray(wiou, dtype=np.float64).ravel()
        if not (src.shape == dst.shape == w.shape):
            raise ShapeError("edges", (src.shape[0], dst.shape[0], w.shape[0]), "[E] each")
        if src.size and (min(src.min(), dst.min()) < 0 or max(src.max(), dst.max()) >= n_nodes):
            raise ValueError(f"edge node ids must lie in [0, {n_nodes}), got "
                             f"[{min(src.min(), dst.min())}, {max(src.max(), dst.max())}]")
        keep = (src != dst) & (w > 0) & np.isfinite(w)
        a = np.concatenate([src[keep], dst[keep]])
        b = np.concatenate([dst[keep], src[keep]])
        ww = np.concatenate([w[keep], w[keep]])
        # dedupe (a, b): keep the highest weight
        order = np.lexsort((-ww, b, a))
        a, b, ww = a[order], b[order], ww[order]
        first = np.ones(a.size, dtype=bool)
        first[1:] = (a[1:] != a[:-1]) | (b[1:] != b[:-1])
        a, b, ww = a[first], b[first], ww[first]
        indptr = np.zeros(n_nodes + 1, dtype=np.int64)
        np.add.at(indptr, a + 1, 1)
        indptr = np.cumsum(indptr)
        return cls(int(n_train), int(n_nodes), indptr, b, ww)

    def neighbours(self, node: int) -> tuple[np.ndarray, np.ndarray]:
        """``(nodes [k], wiou [k])`` adjacent to ``node``, sorted by node id."""
        lo, hi = self.indptr[node], self.indptr[node + 1]
        return self.indices[lo:hi], self.weights[lo:hi]


@dataclass(frozen=True)
class ReferenceChoice:
    """The reference chosen for one free view.

    Attributes:
        train_index: the reference training view (0 .. T-1).
        rule: ``"wiou_direct"`` (WIoU at the final pose), ``"graph_direct"``,
            ``"graph_2hop"`` (stored graph), ``"pose"`` or ``"pose_fallback"``.
        score: the WIoU (direct), path score (2-hop) or pose distance (pose rules).
        via: the intermediate node of a 2-hop path, else -1.
    """

    train_index: int
    rule: str
    score: float
    via: int = -1


class TrainOverlap:
    """WIoU (Eq. 3) between any cameras and every training view, from the certainty grid.

    The training views' visibility of the non-empty voxels is computed once (on the first
    call, so building one that is never used costs nothing); a call computes
    the visibility of the given cameras with the same rule and one row of the Gram product
    ``I = M diag(C) M^T`` per camera against the training rows. Without an angle kernel the
    result equals the corresponding entries of ``view_graph.wiou_matrix`` over training +
    given cameras (no top-k truncation, no threshold).

    With ``angle_deg = (full, zero)`` (ours, a view-direction-aware WIoU) a voxel seen by both
    views counts in the intersection with weight ``kappa``: 1 when the angle at the voxel
    centre between the directions to the two camera centres is at most ``full`` degrees,
    falling linearly to 0 at ``zero``:

        WIoU_a(i, j) = I_a / (f_i + f_j - I_a),  I_a = sum_k C_k M_ik M_jk kappa_ijk,

    so two views that see the same certain voxels *from similar directions* score high, and
    views from the opposite side score low (frustum visibility alone cannot tell them apart).
    ``I_a <= I`` keeps the value in [0, 1]; ``angle_deg=None`` is Eq. 3.

    Args:
        grid: the certainty grid (``certainty.CertaintyGrid``).
        train_cams: T training cameras.
        visibility: ``schemas.select.VisibilityConfig`` (frustum / occlusion), None = default.
        angle_deg: ``(full, zero)`` degrees of the angle kernel, or None.
        chunk: training views per block of the angle kernel (bounds memory).
    """

    def __init__(self, grid, train_cams: Cameras, visibility=None,
                 angle_deg: tuple[float, float] | None = None, chunk: int = 64) -> None:
        self.grid, self.visibility = grid, visibility
        self.n_train = len(train_cams)
        self._train_cams = train_cams
        if angle_deg is not None:
            full, zero = map(float, angle_deg)
            if not 0.0 <= full <= zero:
                raise ValueError(f"angle_deg needs 0 <= full <= zero, got {angle_deg}")
            angle_deg = (full, zero)
        self.angle_deg, self.chunk = angle_deg, max(1, int(chunk))
        self._vis = None

    def _prepare(self) -> None:
        from freescale_core.select.visibility import compute_visibility

        self._vis = compute_visibility(self._train_cams, self.grid, self.visibility,
                                       cells_per_axis=0)
        self._rows = self._vis.weighted_rows(np.arange(self.n_train), np.float64)
        self._f = self._vis.score / self._vis.norm
        self._centres = self._train_cams.centers
        if self.angle_deg is not None:
            self._vox = self.grid.nonzero()[1]  # same order as the visibility (no cells)

    def __call__(self, cams: Cameras) -> np.ndarray:
        """``[n, T]`` WIoU of each camera in ``cams`` with each training view (0 = no shared
        certain voxel)."""
        from freescale_core.select.view_graph import wiou_from_inter
        from freescale_core.select.visibility import compute_visibility

        if len(cams) == 0:
            return np.zeros((0, self.n_train))
        if self._vis is None:
            self._prepare()
        vis = compute_visibility(cams, self.grid, self.visibility, cells_per_axis=0)
        f = vis.score / vis.norm
        if self.angle_deg is None:
            inter = vis.weighted_rows(np.arange(len(cams)), np.float64) @ self._rows.T
            return wiou_from_inter(inter, f, self._f)
        from freescale_core.freeviews.rectify_image import angle_weight

        full, zero = self.angle_deg
        Cn = vis.weights / vis.norm
        M = vis.dense()
        seen = [np.flatnonzero(m) for m in M]
        unit = []  # per query camera: unit directions from its seen voxels to its centre
        for k, c in zip(seen, cams.centers):
            a = self._vox[k] - c
            unit.append(a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-300))
        inter = np.zeros((len(cams), self.n_train))
        for t0 in range(0, self.n_train, self.chunk):  # unpack training rows once per chunk
            t1 = min(self.n_train, t0 + self.chunk)
            Mt = self._vis.dense(np.arange(t0, t1))
            for i, (k, a) in enumerate(zip(seen, unit)):
                if k.size == 0:
                    continue
                b = self._vox[k][None] - self._centres[t0:t1, None]
                b /= np.maximum(np.linalg.norm(b, axis=2, keepdims=True), 1e-300)
                cos = np.clip(np.einsum("tkd,kd->tk", b, a), -1.0, 1.0)
                kap = angle_weight(np.degrees(np.arccos(cos)), full, zero) * Mt[:, k]
                inter[i, t0:t1] = kap @ Cn[k]
        return wiou_from_inter(inter, f, self._f)


def _argmax_lowest(values: np.ndarray, ids: np.ndarray) -> int:
    """Position of the max value; ties go to the lowest id."""
    best = values.max()
    cand = np.flatnonzero(values == best)
    return int(cand[np.argmin(ids[cand])])


def graph_reference(graph: ViewGraph, node: int, two_hop_score: str = "product"
                    ) -> ReferenceChoice | None:
    """Reference by the view graph: best direct training neighbour, else best 2-hop path.

    Args:
        graph: the view graph.
        node: the free view's node id (``T + candidate index``).
        two_hop_score: ``"product"`` or ``"min"`` of the two WIoUs on the path.
    Returns:
        The choice, or None when no training view is within two hops.
    """
    T = graph.n_train
    nb, w = graph.neighbours(node)
    direct = nb < T
    if direct.any():
        k = _argmax_lowest(w[direct], nb[direct])
        return ReferenceChoice(int(nb[direct][k]), "graph_direct", float(w[direct][k]))
    best: tuple[float, int, int] | None = None  # (score, -train, via) compared lexicographically
    for u, w_vu in zip(nb, w):
        nb2, w2 = graph.neighbours(int(u))
        m = nb2 < T
        if not m.any():
            continue
        scores = w_vu * w2[m] if two_hop_score == "product" else np.minimum(w_vu, w2[m])
        k = _argmax_lowest(scores, nb2[m])
        cand = (float(scores[k]), -int(nb2[m][k]), int(u))
        if best is None or cand[:2] > best[:2]:
            best = cand
    if best is None:
        return None
    return ReferenceChoice(-best[1], "graph_2hop", best[0], best[2])


def pose_distances(train_world_from_cam: np.ndarray, world_from_cam: np.ndarray,
                   rotation_weight: float = 1.0) -> np.ndarray:
    """Difix3D-style pose distance from one camera to every training camera.

    Args:
        train_world_from_cam: ``[T, 4, 4]``.
        world_from_cam: ``[4, 4]``.
        rotation_weight: weight of the rotation angle (radians).
    Returns:
        ``[T]`` distances ``|dc| / L + rotation_weight * angle``.
    """
    Tw = np.asarray(train_world_from_cam, dtype=np.float64)
    if Tw.ndim != 3 or Tw.shape[1:] != (4, 4) or Tw.shape[0] == 0:
        raise ShapeError("train_world_from_cam", Tw.shape, "[T>=1, 4, 4]")
    centres = Tw[:, :3, 3]
    L = float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    if not L > 1e-12:
        L = 1.0
    P = np.asarray(world_from_cam, dtype=np.float64)
    dt = np.linalg.norm(centres - P[:3, 3], axis=1) / L
    R = Tw[:, :3, :3]
    ang = np.radians(rotation_angle_deg(R, np.broadcast_to(P[:3, :3], R.shape)))
    return dt + rotation_weight * ang


def pose_reference(train_world_from_cam: np.ndarray, world_from_cam: np.ndarray,
                   rotation_weight: float = 1.0, rule: str = "pose") -> ReferenceChoice:
    """Reference by smallest pose distance (ties: lowest index)."""
    d = pose_distances(train_world_from_cam, world_from_cam, rotation_weight)
    k = int(np.argmin(d))
    return ReferenceChoice(k, rule, float(d[k]))


def select_reference(cfg: ReferenceConfig, train_world_from_cam: np.ndarray,
                     world_from_cam: np.ndarray, graph: ViewGraph | None = None,
                     node: int | None = None, overlap: np.ndarray | None = None
                     ) -> ReferenceChoice:
    """Stage 10 reference for one free view, by the configured rule.

    Args:
        cfg: rule and weights.
        train_world_from_cam: ``[T, 4, 4]`` training poses.
        world_from_cam: ``[4, 4]`` the free view's (final) pose.
        graph: the stored view graph (graph rule, steps 1-2; without it and without
            ``overlap`` the pose rule is used and labelled ``pose_fallback``).
        node: the free view's node id in ``graph``.
        overlap: ``[T]`` WIoU of the free view at its final pose with every training view
            (:class:`TrainOverlap`); used by the graph rule when ``cfg.overlap ==
            "final_pose"``.
    Returns:
        The choice; its ``rule`` says which rule actually decided.
    """
    if cfg.rule == "graph":
        if overlap is not None and cfg.overlap == "final_pose":
            ov = np.asarray(overlap, dtype=np.float64).ravel()
            n_train = np.asarray(train_world_from_cam).shape[0]
            if ov.shape[0] != n_train:
                raise ShapeError("overlap", ov.shape, f"[{n_train}]")
            ok = np.isfinite(ov) & (ov > 0)
            if ok.any():
                k = _argmax_lowest(np.where(ok, ov, -1.0), np.arange(ov.size))
                return ReferenceChoice(k, "wiou_direct", float(ov[k]))
        if graph is not None and node is not None:
            choice = graph_reference(graph, node, cfg.two_hop_score)
            if choice is not None:
                return choice
        return pose_reference(train_world_from_cam, world_from_cam, cfg.rotation_weight,
                              rule="pose_fallback")
    return pose_reference(train_world_from_cam, world_from_cam, cfg.rotation_weight)
