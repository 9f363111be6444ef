"""The published layout of one scene version, in one place: the views table, the view graph,
the zarr arrays and the pictures, built from the stage outputs (the writer) and read back
(``world_from_cam_column``). ``docs/STORE.md`` documents every column for users.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from freescale_core.errors import StoreError

if TYPE_CHECKING:  # the writer's inputs; readers of the layout import none of the stages
    from freescale_core.freeviews.run import FreeViewResult
    from freescale_core.scene.scene import Scene


# views.parquet columns that always exist (later stages add quality columns).
VIEW_COLUMNS = [
    "view_id", "kind", "mode", "disposition", "world_from_cam",
    "fx", "fy", "cx", "cy", "width", "height",
]


def views_table(columns: dict[str, Any]) -> pa.Table:
    """Build a ``views.parquet`` table from column arrays.

    ``world_from_cam`` may be given as ``[N, 4, 4]``; it is stored as 16 float64 row-major
    (OpenCV axes). Required columns: :data:`VIEW_COLUMNS`.
    """
    missing = [c for c in VIEW_COLUMNS if c not in columns]
    if missing:
        raise StoreError(f"views table is missing columns {missing}")
    out = {}
    n = len(columns["view_id"])
    for k, v in columns.items():
        if k == "world_from_cam" or (isinstance(v, np.ndarray) and v.ndim == 3):
            arr = np.asarray(v, dtype=np.float64).reshape(n, 16)
            out[k] = pa.FixedSizeListArray.from_arrays(pa.array(arr.ravel()), 16)
        else:
            out[k] = pa.array(np.asarray(v).tolist() if isinstance(v, np.ndarray) else list(v))
    return pa.table(out)


def graph_table(src: np.ndarray, dst: np.ndarray, wiou: np.ndarray,
                distance: np.ndarray | None = None) -> pa.Table:
    """``view_graph.parquet``: one row per undirected edge (``src < dst``, view ids).

    ``wiou`` is the edge's weighted IoU (NaN in the pose-distance ablation, which has none);
    ``distance`` the pose distance that linked the pair in that ablation (NaN otherwise).
    """
    n = len(np.asarray(src))
    dist = np.full(n, np.nan) if distance is None else np.asarray(distance, np.float64)
    return pa.table({"src": pa.array(np.asarray(src, np.int64)),
                     "dst": pa.array(np.asarray(dst, np.int64)),
                     "wiou": pa.array(np.asarray(wiou, np.float32)),
                     "distance": pa.array(dist.astype(np.float32))})


def world_from_cam_column(table: pa.Table) -> np.ndarray:
    """``[N, 4, 4]`` poses from a views table's ``world_from_cam`` column."""
    col = table.column("world_from_cam").combine_chunks()
    return np.asarray(col.flatten().to_numpy(zero_copy_only=False), np.float64).reshape(-1, 4, 4)


def build_views_table(scene: Scene, sel, fv: FreeViewResult | None, cfg=None) -> dict:
    """Columns of ``views.parquet``: training views, then every candidate.

    With ``cfg`` (a ``FreeViewConfig``) the thresholds each rendered view was judged by are
    recorded beside its scores: ``thr_black_ratio`` (pass if <=), ``thr_brisque`` (pass if <,
    the stage-9 threshold when one was applied) and ``thr_depth_validity`` (pass if >).
    """
    from freescale_core.freeviews.trust import TRUST_COLUMNS

    T, C = int(sel.n_train), len(sel.candidates)
    cams = scene.cameras
    n = T + C
    wfc = np.concatenate([cams.world_from_cam, sel.candidates.world_from_cam])
    cols: dict = {
        "view_id": np.arange(n, dtype=np.int64),
        "kind": ["train"] * T + ["candidate"] * C,
        "mode": ["train"] * T + list(sel.modes),
        "disposition": [str(d) for d in sel.disposition],
        "world_from_cam": wfc,
        "fx": np.concatenate([cams.fx, sel.candidates.fx]),
        "fy": np.concatenate([cams.fy, sel.candidates.fy]),
        "cx": np.concatenate([cams.cx, sel.candidates.cx]),
        "cy": np.concatenate([cams.cy, sel.candidates.cy]),
        "width": np.concatenate([cams.width, sel.candidates.width]).astype(np.int64),
        "height": np.concatenate([cams.height, sel.candidates.height]).astype(np.int64),
        "name": list(scene.image_names) + [""] * C,
        # position of each training view in the source's capture order (-1: candidates)
        "capture_index": np.concatenate([np.argsort(np.asarray(
            getattr(scene, "capture_order", None) if getattr(scene, "capture_order", None)
            is not None else np.arange(T))),
                                         np.full(C, -1)]).astype(np.int64),
        "traj_id": np.concatenate([np.full(T, -1), sel.traj_id]).astype(np.int64),
        "frame_idx": np.concatenate([np.full(T, -1), sel.frame_idx]).astype(np.int64),
        "anchor_idx": np.concatenate([np.arange(T), sel.anchor_idx]).astype(np.int64),
        "perturbed": np.concatenate([np.zeros(T, bool), sel.perturbed]).astype(bool),
        "infeasible_reason": [""] * T + [str(x) for x in sel.infeasible_reason],
        "suppress_reason": [str(x) for x in sel.suppress_reason],
        "score_f": np.asarray(sel.score, dtype=np.float64),
        "nms_overlap": np.asarray(sel.nms_overlap, dtype=np.float64),
        "wiou_to_train": np.asarray(sel.wiou_to_train, dtype=np.float64),
    }
    nan = np.full(n, np.nan)
    extra = {k: nan.copy() for k in ("brisque", "black_ratio", "depth_validity", "rect_s",
                                      "brisque_rectified", "pred_psnr_rectified", "gt_psnr",
                                      "gt_psnr_render",
                                      *TRUST_COLUMNS)}
    passed = np.zeros(n, bool)
    rect_steps = np.zeros(n, np.int64)
    reference = np.full(n, -1, np.int64)
    free_index = np.full(n, -1, np.int64)
    ref_rule = [""] * n
    rectifier = [""] * n
    reject = [""] * n
    disp = cols["disposition"]
    if fv is not None:
        final_pos = {int(c): k for k, c in enumerate(fv.final_candidates)}
        for r in fv.records:
            v = T + int(r.candidate)
            wfc[v] = r.world_from_cam  # the pose of the stored image (after rectification)
            for k in ("fx", "fy", "cx", "cy", "width", "height"):  # ... and its intrinsics
                cols[k][v] = getattr(r, k)
            extra["brisque"][v] = r.brisque
            extra["black_ratio"][v] = r.black_ratio
            extra["depth_validity"][v] = r.depth_validity
            extra["rect_s"][v] = 1.0 if r.passed_first else r.rect_step
            extra["brisque_rectified"][v] = r.brisque_rectified
            extra["pred_psnr_rectified"][v] = getattr(r, "pred_psnr_rectified", np.nan)
            for k in TRUST_COLUMNS:  # trust scores and predicted PSNR (issue 19)
                extra[k][v] = getattr(r, k, np.nan)
            passed[v] = r.passed
            rect_steps[v] = r.n_rect_steps
            reference[v] = r.reference_view
            ref_rule[v] = r.reference_rule
            rectifier[v] = r.rectifier
            if r.final:
                disp[v] = "free_view"
                free_index[v] = final_pos[int(r.candidate)]
                gt = getattr(fv, "gt", {}).get(int(r.candidate))
                if gt is not None:
                    extra["gt_psnr_render"][v], extra["gt_psnr"][v] = gt
            else:
                disp[v] = "rejected"
                reject[v] = r.fail_reasons if not r.passed else "final_selection"
    if fv is not None and cfg is not None:
        rendered = np.isfinite(extra["brisque"])
        trust_f = getattr(getattr(cfg, "trust", None), "filter", "paper") == "trust"
        trust_r = getattr(cfg.final, "rank_by", "brisque") == "trust"
        thr_b = cfg.quality.brisque_max if not trust_f else np.inf
        if np.isfinite(fv.brisque_threshold) and not trust_r:
            thr_b = min(thr_b, float(fv.brisque_threshold))
        thr_d = cfg.quality.depth_validity_min if not trust_f else -np.inf
        thr_p = -np.inf  # the predicted-PSNR threshold (pass if >=)
        if trust_f:
            thr_p = cfg.trust.min_psnr
        if trust_r and np.isfinite(fv.brisque_threshold):
            thr_p = max(thr_p, float(fv.brisque_threshold))
        for name, val in (("thr_black_ratio", cfg.quality.black_ratio_max), ("thr_brisque", thr_b),
                          ("thr_depth_validity", thr_d), ("thr_pred_psnr", thr_p)):
            cols[name] = np.where(rendered, val, np.nan)
    cols.update(extra)
    cols.update({"passed": passed, "rect_steps": rect_steps, "reference_view": reference,
                 "reference_rule": ref_rule, "rectifier": rectifier, "reject_reason": reject,
                 "free_index": free_index, "world_from_cam": wfc, "disposition": disp})
    return cols


def append_heldout_rows(cols: dict, heldout: Scene) -> dict:
    """Append the held-out cameras of an ``ood`` / ``every8`` split as rows with kind and
    disposition ``heldout`` (view ids after the candidates; in no graph edge). They were seen
    by no generation stage; evaluations read their poses and photos from here."""
    n0, H = len(cols["view_id"]), len(heldout)
    cams = heldout.cameras
    given = {"view_id": np.arange(n0, n0 + H, dtype=np.int64), "kind": ["heldout"] * H,
             "mode": ["heldout"] * H, "disposition": ["heldout"] * H,
             "world_from_cam": cams.world_from_cam, "fx": cams.fx, "fy": cams.fy,
             "cx": cams.cx, "cy": cams.cy, "width": np.asarray(cams.width, np.int64),
             "height": np.asarray(cams.height, np.int64), "name": list(heldout.image_names)}
    out = {}
    for k, v in cols.items():
        if k in given:
            add = given[k]
        else:
            a = np.asarray(v)
            if a.dtype.kind == "f":
                add = np.full((H,) + a.shape[1:], np.nan)
            elif a.dtype.kind in "iu":
                add = np.full((H,) + a.shape[1:], -1, a.dtype)
            elif a.dtype.kind == "b":
                add = np.zeros(H, bool)
            else:
                add = [""] * H
        if isinstance(v, list):
            out[k] = list(v) + list(add)
        else:
            out[k] = np.concatenate([np.asarray(v), np.asarray(add, dtype=np.asarray(v).dtype)])
    return out


def link_or_copy(src: Path, dst: Path) -> None:
    """A copy of ``src`` at ``dst`` that owns its bytes (reflink where the file system has
    one, else a copy; :func:`~freescale_core.store.store.own_copy`): a version or an export
    never shares an inode with a user's photo, so editing one never changes the other."""
    from freescale_core.store.store import own_copy

    own_copy(src, dst)


def write_training_inputs(out: Path, scene: Scene) -> None:
    """Make the version self-contained: the pinhole training images the Scene was built from
    (undistorted copies for distorted sources) under ``images/<name>`` and the sparse points
    as ``points.parquet`` (x, y, z float64; r, g, b uint8)."""
    import pyarrow as pa

    from freescale_core.errors import MissingInputError

    # (a scene-like object without image files, e.g. a test double, publishes no images)
    for src, name in zip(getattr(scene, "image_paths", None) or [], scene.image_names):
        if not Path(src).is_file():
            raise MissingInputError(scene.scene_id, "training image to publish is missing", src)
        link_or_copy(Path(src), out / "images" / name)
    xyz = np.asarray(getattr(scene, "points_xyz", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    rgb = np.asarray(getattr(scene, "points_rgb", np.zeros((0, 3))), np.uint8).reshape(-1, 3)
    pq.write_table(pa.table({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                             "r": rgb[:, 0], "g": rgb[:, 1], "b": rgb[:, 2]}),
                   out / "points.parquet")


def _free_view_size(scene: Scene, sel, cfg) -> tuple[int, int]:
    """(H, W) a free view of this scene would have (for empty ``freeviews/`` arrays)."""
    cams = sel.candidates if len(sel.candidates) else scene.cameras
    scale = float(getattr(cfg, "render_scale", 1.0) or 1.0)
    if scale != 1.0:
        cams = cams.scaled(scale)
    return int(np.max(cams.height)), int(np.max(cams.width))


def write_free_view_arrays(root, fv: FreeViewResult, view_ids: np.ndarray) -> None:
    """The ``freeviews/`` group of ``arrays.zarr`` for the final views of ``fv``."""
    # One array for all views; views smaller than the largest (per-camera undistortion
    # gives slightly different sizes) are zero-padded at the bottom/right, and
    # freeviews/size holds each view's (height, width).
    H = max(im.shape[0] for im in fv.rgb)
    W = max(im.shape[1] for im in fv.rgb)
    N = len(fv.rgb)
    rgb_all = np.zeros((N, H, W, 3), np.uint8)
    dep_all = np.zeros((N, H, W), np.float32)
    sizes = np.zeros((N, 2), np.int64)
    for k, (im, d) in enumerate(zip(fv.rgb, fv.depth)):
        h, w = im.shape[:2]
        rgb_all[k, :h, :w] = im
        dep_all[k, :h, :w] = d
        sizes[k] = (h, w)
    fvg = root.create_group("freeviews")
    rgb = fvg.create_array("rgb", shape=(N, H, W, 3), dtype="uint8",
                           chunks=(1, H, W, 3), shards=(min(N, 64), H, W, 3))
    rgb[:] = rgb_all
    dep = fvg.create_array("depth", shape=(N, H, W), dtype="float32",
                           chunks=(1, H, W), shards=(min(N, 64), H, W))
    dep[:] = dep_all
    fvg.create_array("size", data=sizes)
    fvg.create_array("view_id", data=view_ids)
    if any(r.rectifier not in ("", "none") for r in fv.records if r.final):
        # the image rectifier changed the images: keep the raw renders beside them
        raw = np.zeros((N, H, W, 3), np.uint8)
        for k, im in enumerate(fv.rgb_render):
            raw[k, :im.shape[0], :im.shape[1]] = im
        a = fvg.create_array("rgb_render", shape=(N, H, W, 3), dtype="uint8",
                             chunks=(1, H, W, 3), shards=(min(N, 64), H, W, 3))
        a[:] = raw
    conf = getattr(fv, "confidence", None) or []
    if len(conf) == N:  # the fixer's per-pixel confidence, 0..255 = 0..1
        c8 = np.zeros((N, H, W), np.uint8)
        for k, c in enumerate(conf):
            c8[k, :c.shape[0], :c.shape[1]] = np.clip(np.rint(c * 255.0), 0, 255)
        a = fvg.create_array("confidence", shape=(N, H, W), dtype="uint8",
                             chunks=(1, H, W), shards=(min(N, 64), H, W))
        a[:] = c8


def write_scene_outputs(out: Path, scene: Scene, sel, fv: FreeViewResult | None,
                        gaussians_ply: Path, cfg=None, heldout: Scene | None = None) -> dict:
    """Write one complete scene version into ``out`` (a staging folder). Returns counts.

    ``scene`` holds the views the generation used; ``heldout`` (the held-out views of an
    evaluation split, or None) adds rows of kind ``heldout`` to ``views.parquet``.
    """
    import zarr

    cols = build_views_table(scene, sel, fv, cfg)
    if heldout is not None and len(heldout):
        cols = append_heldout_rows(cols, heldout)
    pq.write_table(views_table(cols), out / "views.parquet")
    pq.write_table(graph_table(sel.edges.src, sel.edges.dst, sel.edges.wiou,
                               getattr(sel.edges, "distance", None)),
                   out / "view_graph.parquet")
    root = zarr.open_group(str(out / "arrays.zarr"), mode="w")
    sel.grid.to_zarr(root)
    n_free = 0
    if fv is not None and fv.n_final:
        T = int(sel.n_train)
        write_free_view_arrays(root, fv, T + np.asarray(fv.final_candidates, np.int64))
        n_free = int(len(fv.rgb))
    else:
        # No free view: the same arrays, empty ([0, H, W, 3]), so that readers never need a
        # special case (the manifest's empty_reason says why there are none).
        H, W = _free_view_size(scene, sel, cfg)
        fvg = root.create_group("freeviews")
        fvg.create_array("rgb", shape=(0, H, W, 3), dtype="uint8", chunks=(1, H, W, 3))
        fvg.create_array("depth", shape=(0, H, W), dtype="float32", chunks=(1, H, W))
        fvg.create_array("size", shape=(0, 2), dtype="int64", chunks=(1, 2))
        fvg.create_array("view_id", shape=(0,), dtype="int64", chunks=(1,))
    from freescale_core.store.figures import save_figures

    save_figures(out, scene, sel, fv, cols,
                 int(sel.n_train) + np.asarray(fv.final_candidates, np.int64) if n_free else None)
    if gaussians_ply.is_file():
        from freescale_core.store.store import link_store_file

        link_store_file(gaussians_ply, out / "gaussians.ply")  # _work's, replaced atomically
    write_training_inputs(out, scene)
    if heldout is not None:  # the held-out photos too, for evaluations (never trained on)
        for src, name in zip(heldout.image_paths, heldout.image_names):
            link_or_copy(Path(src), out / "images" / name)
    disp = cols["disposition"]
    counts = {"n_train_views": int(sel.n_train), "n_free_views": n_free,
              "n_heldout_views": 0 if heldout is None else len(heldout),
              "n_rejected": int(sum(d == "rejected" for d in disp)),
              "n_edges": int(len(sel.edges))}
    return counts
