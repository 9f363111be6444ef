"""How well a fixer does on a store's scenes: held-out photos and, on procedural scenes,
free views against the exact renderer (``freescale fixer score``).

Held-out: the store's reconstruction (``_work/gaussians.ply``, trained on the training views
of the store's ``recon_split`` only) is rendered at the held-out cameras; the render
(``none``), the ``reproject`` rectifier with the nearest training photo and the fixer with its
``k`` nearest training photos are scored against the held-out photos, which neither the
reconstruction nor (when it was trained without this scene) the fixer saw. Images are at the
pairs' size (long side ``long_side``); PSNR / SSIM over the scored pixels (object pixels on a
masked capture).

Free views (procedural scenes whose folder holds ``scene.json``): each published free view's
pose is rendered at the free view's size, fixed the same way, and scored against the scene's
exact image at that pose (``oracle_psnr_raw`` / ``oracle_psnr_fixed``), with the Spearman
correlation of the per-view mean confidence with the true per-view error.
"""

from __future__ import annotations

import math
import pickle
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from freescale_core.eval.fixer_pairs import _scene_pixels, view_pair
from freescale_core.freeviews.rectify_image import RenderedView, ReprojectRectifier

__all__ = ["score_images", "score_scene", "score_store", "spearman"]


def score_images(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None
                 ) -> tuple[float, float]:
    """``(PSNR, SSIM)`` of float ``[H, W, 3]`` images over ``mask`` (the recon metric)."""
    from freescale_core.recon.losses import masked_psnr_ssim

    m = None if mask is None or np.all(mask) else torch.from_numpy(np.asarray(mask, bool))
    return masked_psnr_ssim(torch.from_numpy(np.asarray(img, np.float64)),
                            torch.from_numpy(np.asarray(ref, np.float64)), m)


def spearman(a: Sequence[float], b: Sequence[float]) -> float:
    """Spearman rank correlation (average ranks for ties); NaN for fewer than 3 values."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if len(a) < 3:
        return float("nan")

    def rank(x):
        order = np.argsort(x, kind="stable")
        r = np.empty(len(x))
        r[order] = np.arange(len(x))
        for v in np.unique(x):  # ties share the mean rank
            m = x == v
            r[m] = r[m].mean()
        return r

    ra, rb = rank(a), rank(b)
    if ra.std() == 0 or rb.std() == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def _load(store: str | Path, scene_id: str):
    from freescale_core.scene.ply import read_background, read_ply
    from freescale_core.store.reader import FreeViewSet
    from freescale_core.store.store import Store

    st = Store(store)
    work = st.work_dir(scene_id)
    ply, pkl = work / "gaussians.ply", work / "scene.pkl"
    if not (ply.is_file() and pkl.is_file()):
        raise FileNotFoundError(f"scene '{scene_id}': no reconstruction in the store "
                                f"({ply if not ply.is_file() else pkl} is missing)")
    with open(pkl, "rb") as f:
        scene = pickle.load(f)
    cfg = (FreeViewSet.open(store, scene_id).config() or {}).get("config", {})
    recon = cfg.get("recon", {})
    bg = read_background(ply, tuple(recon.get("background", (0.0, 0.0, 0.0))), scene_id)
    source = st.read_status(scene_id).get("source")
    return scene, read_ply(ply, scene_id=scene_id), cfg, bg, recon.get("raster_backend",
                                                                       "auto"), source


def score_scene(store: str | Path, scene_id: str, fixer, long_side: int = 256,
                max_views: int = 0, free_views: bool = True) -> dict:
    """One scene's scores (see the module docstring). ``fixer`` is a
    :class:`~freescale_core.fixer.rectifier.FixerRectifier`."""
    from freescale_core.freeviews.run import make_render_fn

    scene, g, cfg, bg, backend, source = _load(store, scene_id)
    split = cfg.get("recon_split", "all")
    train, test = scene.split(split)
    out = {"scene_id": scene_id, "recon_split": split, "heldout_views": 0,
           "heldout_psnr_raw": math.nan, "heldout_psnr_fixed": math.nan,
           "heldout_psnr_reproject": math.nan, "heldout_ssim_raw": math.nan,
           "heldout_ssim_fixed": math.nan, "heldout_ssim_reproject": math.nan, "note": ""}
    render_fn = make_render_fn(g, bg, backend)
    long = float(max(np.max(scene.cameras.width), np.max(scene.cameras.height)))
    scale = min(1.0, float(long_side) / long)
    tr_cams, tr_photos, _ = _scene_pixels(scene, train, scale)
    rect = ReprojectRectifier()
    k = max(1, fixer.k)
    if len(test) == 0:
        out["note"] = f"no held-out view (recon_split={split})"
    else:
        test = np.asarray(test, np.int64)
        if max_views > 0 and len(test) > max_views:
            test = test[np.unique(np.round(np.linspace(0, len(test) - 1, max_views)).astype(int))]
        cams, targets, masks = _scene_pixels(scene, test, scale)
        cache: dict = {}
        rows = {"raw": [], "fixed": [], "reproject": []}
        for j in range(len(cams)):
            s = view_pair(render_fn, cams, j, tr_cams, tr_photos, cache, k, rect, targets[j],
                          masks[j])
            fixed, _ = fixer.fix([RenderedView(s.render, s.depth, s.alpha, cams.world_from_cam[j],
                                               0, 0, 0, 0)], s.warps[None], s.warp_weight[None])
            r0 = s.meta["refs"][0]
            view = RenderedView(s.render, s.depth, s.alpha, cams.world_from_cam[j],
                                float(cams.fx[j]), float(cams.fy[j]), float(cams.cx[j]),
                                float(cams.cy[j]))
            rep = rect(view, tr_photos[r0], cache[r0]).rgb
            for name, img in (("raw", s.render), ("fixed", fixed[0]), ("reproject", rep)):
                rows[name].append(score_images(img, s.target, s.mask))
        out["heldout_views"] = len(cams)
        for name, v in rows.items():
            out[f"heldout_psnr_{name}"] = float(np.nanmean([p for p, _ in v]))
            out[f"heldout_ssim_{name}"] = float(np.nanmean([q for _, q in v]))
        out["heldout_psnr_per_view"] = {n: [round(p, 3) for p, _ in v] for n, v in rows.items()}
    if free_views and source:
        out.update(_score_free_views(store, scene_id, source, render_fn, scene, train, scale,
                                     fixer, k))
    return out


def _score_free_views(store, scene_id, source, render_fn, scene, train, scale, fixer, k
                      ) -> dict:
    from freescale_core.scene.oracle import ground_truth_oracle
    from freescale_core.store.reader import FreeViewSet

    oracle = ground_truth_oracle(source)
    if oracle is None:
        return {}
    ids, cams = FreeViewSet.open(store, scene_id).cameras("free")
    if len(ids) == 0:
        return {"free_views": 0}
    s0 = float(cams.width[0]) / max(1.0, float(scene.cameras.width[0]))  # free-view scale
    tr_cams, tr_photos, _ = _scene_pixels(scene, train, s0)
    rect = ReprojectRectifier()
    cache: dict = {}
    raw, fixed_p, conf_m, err = [], [], [], []
    for j in range(len(cams)):
        truth = np.asarray(oracle.render_camera(cams, j)[0], np.float32) / 255.0
        s = view_pair(render_fn, cams, j, tr_cams, tr_photos, cache, k, rect, truth)
        f, c = fixer.fix([RenderedView(s.render, s.depth, s.alpha, cams.world_from_cam[j],
                                       0, 0, 0, 0)], s.warps[None], s.warp_weight[None])
        raw.append(score_images(s.render, truth)[0])
        fixed_p.append(score_images(f[0], truth)[0])
        conf_m.append(float(c[0].mean()))
        err.append(float(np.abs(f[0] - truth).mean()))
    return {"free_views": int(len(ids)), "oracle_psnr_raw": float(np.mean(raw)),
            "oracle_psnr_fixed": float(np.mean(fixed_p)),
            "confidence_spearman": -spearman(conf_m, err)}  # high confidence, low error


def score_store(store: str | Path, scenes: Sequence[str] | None = None, checkpoint=None,
                long_side: int = 256, max_views: int = 0) -> list[dict]:
    """:func:`score_scene` for each ``ok`` scene of ``store`` (or ``scenes``)."""
    from freescale_core.freeviews.rectify_image import FixerRectifier
    from freescale_core.store.store import Store

    st = Store(store)
    fixer = FixerRectifier(checkpoint)
    ids = list(scenes) if scenes else [s for s in st.scene_ids()
                                       if st.read_status(s).get("status") == "ok"]
    return [score_scene(store, s, fixer, long_side, max_views) for s in ids]
