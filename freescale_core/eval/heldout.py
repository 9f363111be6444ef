"""Held-out PSNR / SSIM of a sweep point at one fixed evaluation resolution per scene.

The pipeline scores its reconstruction on the held-out views at the point's own *training*
resolution (``recon_test_psnr``): a point trained at half resolution is then scored against
half-resolution photos, which are easier, so points that differ in training resolution are
not comparable. The sweep owns its metric instead: it reloads the point's stored Gaussians
(``_work/gaussians.ply``) and ingested scene (``_work/scene.pkl``), renders the held-out
cameras scaled so the largest held-out image's long side is ``eval_long_side`` (never
upscaled), and compares with the held-out photos area-downscaled (``cv2.INTER_AREA``) to the
same size (:func:`freescale_core.recon.trainer.evaluate`, the function the pipeline uses, with
``long_side`` instead of the training scale). The held-out views, the scaling and so the
resolution depend on the scene only, so every point of a scene is scored at the same size.
"""

from __future__ import annotations

import math
import pickle
import time
from pathlib import Path

from schemas.pipeline import PipelineConfig

# bump when the scoring changes: cached results of the old scoring are then recomputed
HELDOUT_EVAL_VERSION = 1


def heldout_eval_name(long_side: int) -> str:
    """File name of a point's cached held-out score at ``long_side``."""
    return f"heldout_v{HELDOUT_EVAL_VERSION}_L{int(long_side)}.json"


def heldout_at_eval_resolution(store: str | Path, scene_id: str, cfg: PipelineConfig,
                               long_side: int) -> dict:
    """Held-out PSNR / SSIM of the point's reconstruction at the scene's evaluation size.

    Args:
        store: the point's store (one scene, published by ``generate-dataset``).
        scene_id: the scene.
        cfg: the point's resolved config (its ``recon_split``, background, raster backend).
        long_side: the evaluation long side (px) of the largest held-out image.
    Returns:
        ``heldout_psnr``, ``heldout_ssim`` (means over the held-out views; object pixels only
        on a masked scene, as the pipeline), ``eval_long_side``, ``eval_width`` /
        ``eval_height`` (of the first held-out view), ``eval_scale`` (rendered / native size),
        ``heldout_eval_views``, ``heldout_eval_cpu`` (process CPU seconds of the scoring); or
        NaNs and ``heldout_eval_note`` when the point has no reconstruction or no held-out
        view.
    """
    from freescale_core.recon.trainer import evaluate
    from freescale_core.scene.ply import read_ply
    from freescale_core.store.store import Store

    work = Store(store).work_dir(scene_id)
    out = {"heldout_psnr": math.nan, "heldout_ssim": math.nan,
           "eval_long_side": int(long_side), "eval_width": math.nan, "eval_height": math.nan,
           "eval_scale": math.nan, "heldout_eval_views": 0, "heldout_eval_cpu": 0.0,
           "heldout_eval_note": ""}
    ply, pkl = work / "gaussians.ply", work / "scene.pkl"
    if not (ply.is_file() and pkl.is_file()):
        out["heldout_eval_note"] = "no reconstruction in the point's store"
        return out
    with open(pkl, "rb") as f:
        scene = pickle.load(f)
    _, test = scene.split(cfg.recon_split)
    if not len(test):
        out["heldout_eval_note"] = f"no held-out view (recon_split={cfg.recon_split})"
        return out
    c0 = time.process_time()
    g = read_ply(ply, scene_id=scene_id)
    ev = evaluate(g, scene, test, long_side=int(long_side), background=cfg.recon.background,
                  backend=cfg.recon.raster_backend)
    w, h = ev["resolution"][0]
    out.update(heldout_psnr=float(ev["psnr_mean"]), heldout_ssim=float(ev["ssim_mean"]),
               eval_width=float(w), eval_height=float(h),
               eval_scale=float(w) / float(scene.cameras.width[int(test[0])]),
               heldout_eval_views=len(ev["views"]),
               heldout_eval_cpu=time.process_time() - c0)
    return out
