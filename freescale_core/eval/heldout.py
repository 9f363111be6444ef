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

Beside every score the same views get two trivial baselines at the same size
(:func:`trivial_heldout_baselines`): the nearest training photo (by camera centre) copied,
and the mean of the training photos. A reconstruction that does not beat them has learned
nothing the captures did not already show.
"""

from __future__ import annotations

import math
import pickle
import time
from pathlib import Path

import numpy as np

from schemas.pipeline import PipelineConfig

def heldout_eval_name(long_side: int) -> str:
    """File name of a point's cached held-out score at ``long_side``, keyed by the code the
    scoring reaches (an edit of it recomputes the score, freescale_core.codekey)."""
    from freescale_core.codekey import code_key

    return f"heldout_{code_key((__name__,))[:12]}_L{int(long_side)}.json"


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
        ``heldout_eval_views``, ``heldout_eval_cpu`` (process CPU seconds of the scoring),
        ``heldout_nearest_psnr`` / ``heldout_mean_psnr`` (:func:`trivial_heldout_baselines`); or
        NaNs and ``heldout_eval_note`` when the point has no reconstruction or no held-out
        view.
    """
    from freescale_core.recon.trainer import evaluate
    from freescale_core.scene.ply import read_background, read_ply
    from freescale_core.store.store import Store

    st = Store(store)
    work = st.work_dir(scene_id)
    out = {"heldout_psnr": math.nan, "heldout_ssim": math.nan,
           "eval_long_side": int(long_side), "eval_width": math.nan, "eval_height": math.nan,
           "eval_scale": math.nan, "heldout_eval_views": 0, "heldout_eval_cpu": 0.0,
           "heldout_eval_note": "", "heldout_nearest_psnr": math.nan,
           "heldout_mean_psnr": math.nan}
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
    bg = read_background(ply, cfg.recon.background, scene_id)  # learned, when it was
    ev = evaluate(g, scene, test, long_side=int(long_side), background=bg,
                  backend=cfg.recon.raster_backend)
    w, h = ev["resolution"][0]
    out.update(heldout_psnr=float(ev["psnr_mean"]), heldout_ssim=float(ev["ssim_mean"]),
               eval_width=float(w), eval_height=float(h),
               eval_scale=float(w) / float(scene.cameras.width[int(test[0])]),
               heldout_eval_views=len(ev["views"]),
               heldout_eval_cpu=time.process_time() - c0)
    train, _ = scene.split(cfg.recon_split)
    out.update(trivial_heldout_baselines(scene, train, test, int(long_side)))
    return out


def trivial_heldout_baselines(scene, train, test, long_side: int,
                              masks: list[np.ndarray] | None = None) -> dict:
    """Held-out PSNR of two predictions that need no model, at the size
    :func:`freescale_core.recon.trainer.evaluate` scores ``test`` at with ``long_side``:
    ``heldout_nearest_psnr`` (the training photo whose camera centre is nearest, copied) and
    ``heldout_mean_psnr`` (the mean of the training photos); means over the held-out views,
    mask pixels only on a masked scene, and only on ``masks[j]``'s pixels of held-out view
    ``j`` where given (e.g. the co-visible ones). NaN without training or held-out views."""
    import torch

    from freescale_core.recon.losses import masked_psnr
    from freescale_core.recon.trainer import _resize

    train = np.asarray(train, np.int64).reshape(-1)
    test = np.asarray(test, np.int64).reshape(-1)
    out = {"heldout_nearest_psnr": math.nan, "heldout_mean_psnr": math.nan}
    if not len(train) or not len(test):
        return out
    cams = scene.cameras.subset(test)
    long = np.maximum(cams.width, cams.height)
    cams = cams.scaled(float(min(1.0, long_side / long.max())))
    centres = scene.cameras.centers
    masked = getattr(scene, "has_masks", False)
    near, mean = [], []
    cache: dict[tuple[int, int, int], np.ndarray] = {}
    mean_photo: dict[tuple[int, int], np.ndarray] = {}  # per held-out size

    def photo(i: int, w: int, h: int) -> np.ndarray:
        key = (int(i), int(w), int(h))
        if key not in cache:
            cache[key] = _resize(scene.load_image(int(i)), w, h).astype(np.float64) / 255.0
        return cache[key]

    def score(pred: np.ndarray, target: np.ndarray, mask) -> float:
        # the PSNR of the held-out score itself (trainer.evaluate -> masked_psnr_ssim)
        return masked_psnr(torch.from_numpy(pred), torch.from_numpy(target),
                           None if mask is None else torch.from_numpy(np.asarray(mask)))

    for j, i in enumerate(test):
        w, h = int(cams.width[j]), int(cams.height[j])
        target = photo(i, w, h)
        mask = None
        if masked:
            from freescale_core.scene.io.masks import resize_mask

            mask = resize_mask(scene.load_mask(int(i)), w, h)
        if masks is not None:
            if np.shape(masks[j]) != (h, w):
                raise ValueError(f"{scene.scene_id}: mask {j} is {np.shape(masks[j])}, the "
                                 f"held-out view is {h}x{w}")
            mask = np.asarray(masks[j], bool) if mask is None else mask & masks[j]
        k = int(train[np.argmin(np.linalg.norm(centres[train] - centres[i], axis=1))])
        near.append(score(photo(k, w, h), target, mask))
        if (w, h) not in mean_photo:
            mean_photo[(w, h)] = np.mean([photo(t, w, h) for t in train], axis=0)
        mean.append(score(mean_photo[(w, h)], target, mask))
    out.update(heldout_nearest_psnr=float(np.nanmean(near)),
               heldout_mean_psnr=float(np.nanmean(mean)))
    return out
