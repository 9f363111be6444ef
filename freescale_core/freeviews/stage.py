"""The free-view stage adapter: stages 7-10 on a selection, with the renderer and the
reference rule's overlap function built from the stage's inputs.

Plain, testable Python with no Prefect in it (``tasks/`` wraps it).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from freescale_core.scene.images import psnr_u8
from freescale_core.scene.oracle import ground_truth_oracle
from freescale_core.freeviews.run import FreeViewResult, run_freeviews
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.scene import Scene


def make_render_fn(g: Gaussians, background=(0.0, 0.0, 0.0), backend: str = "auto"):
    """``render_fn(world_from_cam, fx, fy, cx, cy, width, height) -> (rgb, depth, alpha)``.

    ``background`` and ``backend`` must be the reconstruction's (``ReconConfig.background``,
    ``ReconConfig.raster_backend``): a model trained on white renders its free views on white.
    ``render_fn.batch(world_from_cam [N, 4, 4], fx [N], ..., height [N])`` renders N cameras
    in one rasterizer call (``raster.render_gaussians_batch``, the same images).
    """
    from freescale_core.raster import render_gaussians, render_gaussians_batch

    bg = tuple(float(v) for v in background)

    def render_fn(world_from_cam, fx, fy, cx, cy, width, height):
        return render_gaussians(g, world_from_cam, fx, fy, cx, cy, int(width), int(height),
                                background=bg, backend=backend)

    def batch(world_from_cam, fx, fy, cx, cy, width, height):
        return render_gaussians_batch(g, world_from_cam, fx, fy, cx, cy, width, height,
                                      background=bg, backend=backend)

    render_fn.batch = batch
    return render_fn


def make_overlap_fn(sel, train_cams, cfg):
    """The graph reference rule's WIoU at the final pose (``references.TrainOverlap``) over
    the selection's certainty grid, or None when the rule does not need it or the selection
    has no grid. ``cfg`` is a ``FreeViewConfig``; the visibility rule is the selection's
    (``sel.config["visibility"]``) unless ``cfg.reference.visibility`` names one."""
    ref = cfg.reference
    if ref.rule != "graph" or ref.overlap != "final_pose" or getattr(sel, "grid", None) is None:
        return None
    from schemas.select import VisibilityConfig

    from freescale_core.freeviews.references import TrainOverlap

    vis = VisibilityConfig.model_validate((getattr(sel, "config", None) or {}).get(
        "visibility", {}))
    if ref.visibility != "selection":
        vis = vis.model_copy(update={"mode": ref.visibility})
    return TrainOverlap(sel.grid, train_cams, vis, ref.overlap_angle_deg)


def run_free_view_stage(scene: Scene, g: Gaussians, sel, cfg, seed: int = 0,
                        scene_path: str | Path | None = None,
                        train_scale: float = 1.0, background=(0.0, 0.0, 0.0),
                        backend: str = "auto", progress=None) -> FreeViewResult:
    """Stages 7-10 on the NMS-selected candidates of ``sel`` (a ``SelectionResult``), then
    on its reserve (``sel.reserve``, in order) while fewer than ``cfg.final.target`` passed.

    Free views are rendered at the reconstruction's training resolution (METHOD stage 7):
    the effective render scale is ``min(cfg.render_scale, train_scale)``, where
    ``train_scale`` is the factor the reconstruction trained at. Rendering a 128-px model at
    640 px only manufactures blur (BRISQUE ~0.9 on kermit, every view rejected).

    When the scene carries a ground-truth oracle (the sample scene), each final view's PSNR
    against the true image at the same pose is recorded (before and after image
    rectification) in ``result.gt`` as ``{candidate: (psnr_render, psnr_final)}``, its
    seconds in ``result.timings["ground_truth"]``.
    """
    T = int(sel.n_train)
    cand = np.asarray(sel.selected, dtype=np.int64) - T
    edges = (sel.edges.src, sel.edges.dst, sel.edges.wiou)
    scale = float(min(cfg.render_scale, train_scale))
    if scale != cfg.render_scale:
        cfg = cfg.model_copy(update={"render_scale": scale})
    reserve = np.asarray(getattr(sel, "reserve", np.zeros(0)), dtype=np.int64) - T
    fv = run_freeviews(scene.cameras, scene.load_image, sel.candidates, cand, edges,
                       make_render_fn(g, background, backend), cfg, seed=seed,
                       overlap_fn=make_overlap_fn(sel, scene.cameras, cfg), progress=progress,
                       grid=getattr(sel, "grid", None),
                       train_masks=scene.load_mask if scene.has_masks else None,
                       reserve=reserve)
    fv.gt = {}
    oracle = ground_truth_oracle(scene_path)
    if oracle is not None:
        t0 = time.perf_counter()
        recs = {r.candidate: r for r in fv.records}
        for k, c in enumerate(fv.final_candidates):
            r = recs[int(c)]
            true_rgb, _ = oracle.render(r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)
            fv.gt[int(c)] = (psnr_u8(fv.rgb_render[k], true_rgb), psnr_u8(fv.rgb[k], true_rgb))
        # an evaluation of the sample scene, not stage work: its own part of the timings
        fv.timings["ground_truth"] = time.perf_counter() - t0
    return fv
