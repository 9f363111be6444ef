"""The selection core: METHOD.md stages 2-6 in one pure function.

``run_selection(gaussians, train_cams, cfg, seed)``:

2. certainty grid (Eq. 1) and the scene-adaptive resolution;
3. candidate cameras (10 trajectory modes);
4. feasibility (outside the box / inside structure);
5. visibility of the non-empty voxels in the training and feasible candidate views, node
   scores f, and (after 6) the view graph among the kept views (Eq. 3, WIoU edges);
6. greedy NMS from the training views (threshold 0.7, K = 500).

View (node) numbering everywhere: training views ``0 .. T-1`` then candidate ``j`` as
``T + j``. ``disposition`` is "train", "infeasible", "suppressed" or "free_view" (kept by NMS,
to be rendered).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from schemas.select import SelectConfig

from freescale_core.geometry.cameras import Cameras
from freescale_core.select.certainty import CertaintyGrid, build_certainty_grid, object_support
from freescale_core.errors import DegenerateSceneError
from freescale_core.select.feasibility import check_feasibility
from freescale_core.scene.gaussians import Gaussians
from freescale_core.select.nms import nms_pose_distance, nms_wiou, top_k_by_score
from freescale_core.select.trajectories import generate_candidates
from freescale_core.select.view_graph import (Edges, camera_spacing, edges_from_matrix, empty_edges,
                                              pose_distance, wiou_matrix)
from freescale_core.select.visibility import compute_visibility
from freescale_core.threads import blas_threads

__all__ = ["SelectionResult", "run_selection"]



@dataclass
class SelectionResult:
    """Everything stages 2-6 produce for one scene.

    Attributes:
        scene_id, seed: provenance.
        config: the ``SelectConfig`` used (``model_dump(mode="json")``).
        grid: the certainty grid (values [R, R, R] float32, [ix, iy, iz]).
        R_adaptive, R_adaptive_reason: the scene-adaptive resolution and why.
        n_train: T.
        candidates: Nc candidate cameras (node ``T + j`` is candidate j).
        modes: ``Nc`` trajectory mode names.
        traj_id, frame_idx, anchor_idx: ``[Nc]`` int provenance of each candidate.
        lookat: ``[Nc, 3]`` look-at point (NaN for modes without one).
        perturbed: ``[Nc]`` bool.
        disposition: ``[T + Nc]`` "train" / "infeasible" / "suppressed" / "free_view".
        infeasible_reason: ``[Nc]`` "" / "outside_box" / "inside_structure".
        suppress_reason: ``[T + Nc]`` "" / "overlap" / "budget" / "zero_score".
        score: ``[T + Nc]`` node score f (Eq. 3; NaN where not evaluated: infeasible
            candidates, or every view in the pose_distance ablation).
        nms_overlap: ``[T + Nc]`` max WIoU to the kept set when NMS decided (pose_distance
            ablation: min pose distance); NaN where not decided.
        wiou_to_train: ``[T + Nc]`` max WIoU of each kept view to the other training views
            (NaN for views not kept or in ablations without WIoU).
        edges: view-graph edges among the kept views (training + free views).
        selected: ``[S]`` node ids of the free views, in acceptance order.
        reserve: ``[R]`` node ids the free-view stage may draw, in order, when fewer than its
            target pass (``NMSConfig.reserve_thresholds``, :func:`nms_reserve`); not in the
            view graph's edges.
        counts: numbers of candidates per outcome, voxels, edges...
        timings: seconds per stage ("grid", "candidates", "feasibility", "visibility",
            "nms", "graph", "total").
        scale: length unit of the candidate stage (world units); up: ``[3]`` world up.
    """

    scene_id: str
    seed: int
    config: dict
    grid: CertaintyGrid
    R_adaptive: int
    R_adaptive_reason: str
    n_train: int
    candidates: Cameras
    modes: list[str]
    traj_id: np.ndarray
    frame_idx: np.ndarray
    anchor_idx: np.ndarray
    lookat: np.ndarray
    perturbed: np.ndarray
    disposition: np.ndarray
    infeasible_reason: np.ndarray
    suppress_reason: np.ndarray
    score: np.ndarray
    nms_overlap: np.ndarray
    wiou_to_train: np.ndarray
    edges: Edges
    selected: np.ndarray
    reserve: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    counts: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)
    scale: float = 1.0
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    @property
    def n_views(self) -> int:
        return self.n_train + len(self.candidates)

    def selected_cameras(self) -> Cameras:
        """The free views' cameras, in acceptance order."""
        return self.candidates.subset(self.selected - self.n_train)


def nms_reserve(vis, T: int, res, cfg: SelectConfig, dtype) -> np.ndarray:
    """The reserve (local visibility rows, in draw order): the overlap-suppressed candidates
    that greedy NMS accepts at each relaxed threshold of ``cfg.nms.reserve_thresholds`` in
    turn, with the training views, the selected views and the reserve so far as the kept
    set; at most ``cfg.nms.reserve_max``. Each pass is the paper's rule at a higher
    threshold, so the reserve stays spread out: the next-least-overlapping views first."""
    kept = np.asarray(res.selected, np.int64)
    left = np.flatnonzero(res.reason == "overlap").astype(np.int64)
    out: list[np.ndarray] = []
    n = 0
    for thr in cfg.nms.reserve_thresholds:
        if n >= cfg.nms.reserve_max or not len(left):
            break
        r = nms_wiou(vis, T, left, thr, cfg.nms.reserve_max - n, cfg.nms.min_score,
                     cfg.graph.block_rows, dtype, kept=kept)
        out.append(r.selected)
        n += len(r.selected)
        kept = np.concatenate([kept, r.selected])
        left = np.setdiff1d(left, r.selected)
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def run_selection(gaussians: Gaussians, train_cams: Cameras, cfg: SelectConfig | None = None,
                  seed: int = 0, scene_id: str = "?",
                  capture_order: np.ndarray | None = None,
                  points: np.ndarray | None = None,
                  train_masks=None) -> SelectionResult:
    """Stages 2-6 for one scene.

    Args:
        gaussians: the reconstruction (validated; NaN -> :class:`DegenerateSceneError`).
        train_cams: T >= 1 training cameras (graph nodes 0 .. T-1).
        cfg: settings (defaults = the paper's numbers).
        seed: same seed, same result.
        scene_id: for errors and provenance.
        capture_order: ``[T]`` capture order of ``train_cams`` (interpolation mode).
        points: ``[P, 3]`` sparse SfM points; with the training cameras they bound the
            certainty box (``cfg.grid.box_anchor_margin``).
        train_masks: ``i -> [H, W]`` bool object mask of training view ``i`` (e.g.
            ``Scene.load_mask``) or None: with masks, Gaussians the masks do not support
            (:func:`~freescale_core.select.certainty.object_support`) are left out of the grid.
    Returns:
        :class:`SelectionResult`.
    """
    cfg = cfg or SelectConfig()
    # every product of the selection under one OpenBLAS setting (its results depend on the
    # thread count; the lease keeps it fixed while scenes of one process overlap)
    with blas_threads(cfg.graph.blas_threads):
        return _run_selection(gaussians, train_cams, cfg, seed, scene_id, capture_order,
                              points, train_masks)


def _run_selection(gaussians, train_cams, cfg, seed, scene_id, capture_order, points,
                   train_masks) -> SelectionResult:
    T = len(train_cams)
    if T == 0:
        raise DegenerateSceneError(scene_id, "no training cameras for view selection")
    if not np.all(np.isfinite(train_cams.world_from_cam)):
        raise DegenerateSceneError(scene_id, "training camera poses are not finite")
    timings: dict[str, float] = {}
    t_all = time.perf_counter()

    t = time.perf_counter()
    mask_counts: dict = {}
    if train_masks is not None:
        keep, mask_counts = object_support(gaussians.means, train_cams, train_masks,
                                           cfg.grid.mask_min_fraction)
        if not keep.any():
            raise DegenerateSceneError(
                scene_id, f"no Gaussian lies inside the object masks (in at least "
                f"{cfg.grid.mask_min_fraction:.0%} of the views that see it, "
                "select.grid.mask_min_fraction): the masks and the reconstruction disagree")
        gaussians = gaussians.subset(np.flatnonzero(keep))
    grid, R_ad, R_reason = build_certainty_grid(gaussians, cfg.grid, scene_id,
                                                camera_centers=train_cams.centers,
                                                points=points)
    timings["grid"] = time.perf_counter() - t

    t = time.perf_counter()
    cs = generate_candidates(train_cams, grid, cfg.candidates, seed, capture_order)
    timings["candidates"] = time.perf_counter() - t
    Nc = len(cs)
    N = T + Nc

    t = time.perf_counter()
    feas = check_feasibility(cs.cameras.centers, grid, cfg.feasibility,
                             train_centers=train_cams.centers, margin=cfg.grid.margin)
    timings["feasibility"] = time.perf_counter() - t
    feas_nodes = T + np.flatnonzero(feas.feasible)

    score = np.full(N, np.nan)
    wiou_train = np.full(N, np.nan)
    edges = empty_edges()
    gdt = np.float32 if cfg.graph.gemm_dtype == "float32" else np.float64
    n_vox = int(np.count_nonzero(grid.values))
    all_cams = Cameras.concat([train_cams, cs.cameras])
    if cfg.graph.mode in ("wiou", "none"):
        t = time.perf_counter()
        vis_nodes = np.concatenate([np.arange(T), feas_nodes])
        vis = compute_visibility(all_cams.subset(vis_nodes), grid, cfg.visibility,
                                 cfg.graph.bound_cells_per_axis if cfg.graph.mode == "wiou" else 0)
        score[vis_nodes] = vis.score
        timings["visibility"] = time.perf_counter() - t
        t = time.perf_counter()
        local_cands = np.arange(T, len(vis_nodes))
        if cfg.graph.mode == "wiou":
            res = nms_wiou(vis, T, local_cands, cfg.nms.wiou_threshold, cfg.nms.max_views,
                           cfg.nms.min_score, cfg.graph.block_rows, gdt)
        else:
            res = top_k_by_score(vis.score, T, local_cands, cfg.nms.max_views, cfg.nms.min_score)
        timings["nms"] = time.perf_counter() - t
        t = time.perf_counter()
        reserve_local = np.zeros(0, np.int64)
        if cfg.graph.mode == "wiou" and cfg.nms.reserve_thresholds and cfg.nms.reserve_max:
            reserve_local = nms_reserve(vis, T, res, cfg, gdt)
        reserve = vis_nodes[reserve_local].astype(np.int64)
        timings["reserve"] = time.perf_counter() - t
        nms_stats = dict(res.stats)
        t = time.perf_counter()
        if cfg.graph.mode == "wiou":
            kept_local = np.concatenate([np.arange(T), res.selected])
            Wk = wiou_matrix(vis, kept_local, gdt)
            kept_nodes = vis_nodes[kept_local]
            s, d, w = edges_from_matrix(Wk, kept_nodes, cfg.graph.edge_threshold, cfg.graph.top_k)
            edges = Edges(s, d, w, np.full(len(s), np.nan))
            Wt = Wk[:, :T].copy()
            Wt[np.arange(T), np.arange(T)] = -np.inf  # a training view vs itself
            mx = Wt.max(axis=1)
            wiou_train[kept_nodes] = np.where(np.isfinite(mx), mx, np.nan)
        timings["graph"] = time.perf_counter() - t
        # map local (visibility-row) results back to node ids
        status = np.full(N, "", dtype="<U10")
        reason = np.full(N, "", dtype="<U10")
        overlap = np.full(N, np.nan)
        status[vis_nodes], reason[vis_nodes] = res.status, res.reason
        overlap[vis_nodes] = res.overlap
        selected = vis_nodes[res.selected]
    else:  # pose_distance ablation: no certainty grid in graph or NMS
        reserve = np.zeros(0, np.int64)
        timings["visibility"] = 0.0
        t = time.perf_counter()
        spacing = camera_spacing(train_cams.centers, cs.scale)
        res = nms_pose_distance(all_cams, T, feas_nodes, spacing, cfg.graph.pose_rot_unit_deg,
                                cfg.nms.pose_threshold, cfg.nms.max_views, seed)
        timings["nms"] = time.perf_counter() - t
        t = time.perf_counter()
        kept = np.concatenate([np.arange(T), res.selected])
        kc = all_cams.subset(kept)
        D = pose_distance(kc, kc, spacing, cfg.graph.pose_rot_unit_deg)
        s, d, dist = edges_from_matrix(D, kept, cfg.nms.pose_threshold, cfg.graph.top_k,
                                       larger_is_closer=False)
        edges = Edges(s, d, np.full(len(s), np.nan), dist)
        timings["graph"] = time.perf_counter() - t
        status, reason, overlap, selected = res.status, res.reason, res.overlap, res.selected
        nms_stats = dict(res.stats)

    disposition = status.copy()
    disposition[:T] = "train"
    disposition[T:][~feas.feasible] = "infeasible"
    timings["total"] = time.perf_counter() - t_all

    counts = {
        "n_train": T,
        "n_candidates": Nc,
        **feas.counts,
        "n_selected": int(len(selected)),
        "n_reserve": int(len(reserve)),
        "n_suppressed_overlap": int(np.sum(reason == "overlap")),
        "n_suppressed_budget": int(np.sum(reason == "budget")),
        "n_zero_score": int(np.sum(reason == "zero_score")),
        "n_voxels_nonempty": n_vox,
        "n_edges": len(edges),
        "lookat_pool_size": int(cs.lookat_pool_size),
        "R": grid.R,
        "R_adaptive": int(R_ad),
        **mask_counts,
        **{f"nms_{k}": int(v) for k, v in nms_stats.items()},
    }
    return SelectionResult(
        scene_id=scene_id, seed=int(seed), config=cfg.model_dump(mode="json"), grid=grid,
        R_adaptive=int(R_ad), R_adaptive_reason=R_reason, n_train=T, candidates=cs.cameras,
        modes=[str(m) for m in cs.mode], traj_id=cs.traj_id, frame_idx=cs.frame_idx,
        anchor_idx=cs.anchor_idx, lookat=cs.lookat, perturbed=cs.perturbed,
        disposition=disposition, infeasible_reason=feas.reason, suppress_reason=reason,
        score=score, nms_overlap=overlap, wiou_to_train=wiou_train, edges=edges,
        selected=selected.astype(np.int64), reserve=reserve, counts=counts, timings=timings, scale=cs.scale,
        up=cs.up)
