"""Training pairs for the fixer, made by the engine from a scene (issue: the fixer network).

Per scene and *fold* a reconstruction is trained on part of the captured views only, then
rendered at the cameras it never saw:

* ``every8``: every 8th view (capture order) held out, the usual 3DGS protocol;
* ``ood``: the last 30% of the capture held out (the far end, like free views off the path);
* ``oracle`` (procedural scenes, which carry their exact renderer ``scene.json``): trained on
  every view, rendered at off-path poses the capture never visited, the target being the
  scene's true image there (the oracle).

A scene whose folder lists held-out views (``heldout.txt``) holds out those for ``every8``
and ``ood`` alike (one fold is then written, ``every8``). Each fold is rendered at several
*budgets*: snapshots of the same training run at fractions of its iteration budget
(under-fitted models, as Difix3D+ pairs use) and the final model.

Each pair holds the render (RGB, depth, alpha), the ``k`` nearest training photos (pose
distance) warped into the view with the rendered depths (``ReprojectRectifier.warp``: its
evidence classes and angle kernel give the per-pixel weight), and the held-out photo. A held-
out photo never enters the reconstruction that renders it: the reconstruction sees only
``train_idx``, and :func:`make_fold_pairs` checks that no held-out index is among them.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from schemas.fixer_pairs import PairsConfig

from freescale_core.errors import FreeScaleError
from freescale_core.fixer.data import FixerSample, write_pair_folder

__all__ = ["PairsConfig", "make_scene_pairs", "make_fold_pairs", "view_pair",
           "nearest_refs", "pairs_code_hash", "LeakError"]

FOLDS = ("every8", "ood", "oracle")


class LeakError(FreeScaleError):
    """A held-out view would enter the reconstruction that renders it."""


def pairs_code_hash() -> str:
    """The code key of pair making (every project module this one reaches, and the
    versions of the dependencies that compute it; :func:`freescale_core.codekey.code_key`)."""
    from freescale_core.codekey import code_key

    return code_key([__name__])


def nearest_refs(train_poses: np.ndarray, pose: np.ndarray, k: int) -> np.ndarray:
    """Indices (into ``train_poses``) of the ``k`` training cameras nearest ``pose`` by the
    Difix3D-style pose distance (centre distance / median radius + rotation angle)."""
    from freescale_core.freeviews.references import pose_distances

    d = pose_distances(train_poses, pose)
    return np.argsort(d, kind="stable")[: int(k)]


def _psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        if not mask.any():
            return float("nan")
        d = d[mask]
    mse = float(d.mean())
    return float("inf") if mse <= 0 else float(-10.0 * np.log10(mse))


def view_pair(render_fn, cams, j: int, train_cams, train_photos: Sequence[np.ndarray],
              ref_renders: dict, k: int, rectifier, target: np.ndarray,
              mask: np.ndarray | None = None) -> FixerSample:
    """One pair: render camera ``j`` of ``cams``, warp the ``k`` nearest training photos.

    Args:
        render_fn: ``(world_from_cam, fx, fy, cx, cy, w, h) -> (rgb, depth, alpha)``.
        cams: the target cameras (already at pair resolution).
        train_cams: the training cameras at pair resolution; ``train_photos`` their photos
            (float [0, 1], same sizes).
        ref_renders: cache ``{train index: RenderedView}`` filled on demand.
        rectifier: a ``ReprojectRectifier`` (its ``warp`` is used).
        target: ``[H, W, 3]`` float target image; ``mask``: scored pixels (default all).
    """
    from freescale_core.freeviews.rectify_image import RenderedView

    T = cams.world_from_cam[j]
    fx, fy, cx, cy = (float(cams.fx[j]), float(cams.fy[j]), float(cams.cx[j]),
                      float(cams.cy[j]))
    W, H = int(cams.width[j]), int(cams.height[j])
    rgb, depth, alpha = render_fn(T, fx, fy, cx, cy, W, H)
    view = RenderedView(rgb, depth, alpha, T, fx, fy, cx, cy)
    refs = nearest_refs(train_cams.world_from_cam, T, k)
    warps = np.zeros((k, H, W, 3), np.float32)
    weight = np.zeros((k, H, W), np.float32)
    angle = np.full((k, H, W), np.nan, np.float32)
    for slot, i in enumerate(refs):
        i = int(i)
        if i not in ref_renders:
            Ti = train_cams.world_from_cam[i]
            r = render_fn(Ti, float(train_cams.fx[i]), float(train_cams.fy[i]),
                          float(train_cams.cx[i]), float(train_cams.cy[i]),
                          int(train_cams.width[i]), int(train_cams.height[i]))
            ref_renders[i] = RenderedView(r[0], r[1], r[2], Ti, float(train_cams.fx[i]),
                                          float(train_cams.fy[i]), float(train_cams.cx[i]),
                                          float(train_cams.cy[i]))
        e = rectifier.warp(view, train_photos[i], ref_renders[i])
        warps[slot] = np.where(e["weight"][..., None] > 0, e["warped"], 0.0)
        weight[slot] = e["weight"]
        if e["angle"] is not None:
            angle[slot] = np.where(e["weight"] > 0, e["angle"], np.nan)
    mask = np.ones((H, W), bool) if mask is None else np.asarray(mask, bool)
    w0 = weight[0] > 0
    return FixerSample(render=rgb, alpha=alpha, depth=depth, warps=warps, warp_weight=weight,
                       warp_angle=np.nan_to_num(angle, nan=0.0), target=target, mask=mask,
                       meta={"k": int(k), "height": H, "width": W,
                             "psnr_render": _psnr(rgb, target, mask),
                             "psnr_warp0": _psnr(warps[0], target, mask & w0),
                             "warp_coverage": float((w0 & mask).mean()),
                             "alpha_mean": float(np.mean(alpha)),
                             "refs": [int(i) for i in refs]})


def _pick(idx: np.ndarray, n: int) -> np.ndarray:
    """At most ``n`` of ``idx``, evenly spaced (all when ``n`` <= 0)."""
    if n <= 0 or len(idx) <= n:
        return idx
    return idx[np.unique(np.round(np.linspace(0, len(idx) - 1, n)).astype(int))]


def _scene_pixels(scene, idx, scale: float):
    """Cameras ``idx`` scaled by ``scale``, their photos (float) and masks at that size."""
    import cv2

    cams = scene.cameras.subset(idx).scaled(scale)
    photos, masks = [], []
    for j, i in enumerate(idx):
        img = scene.load_image(int(i))
        w, h = int(cams.width[j]), int(cams.height[j])
        if img.shape[1] != w or img.shape[0] != h:
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        photos.append(np.asarray(img[..., :3], np.float32) / 255.0)
        m = None
        if getattr(scene, "has_masks", False):
            from freescale_core.scene.io.masks import resize_mask

            m = np.asarray(resize_mask(scene.load_mask(int(i)), w, h), bool)
        masks.append(m)
    return cams, photos, masks


def make_fold_pairs(scene, fold: str, cfg, seed: int = 0, scene_path: str | Path | None = None,
                    log: Callable[[str], None] | None = None) -> tuple[list[FixerSample], dict]:
    """The pairs of one scene and fold (see the module docstring); ``(samples, facts)``.

    Raises:
        LeakError: a held-out view is among the training views of its reconstruction.
        ValueError: unknown fold, or ``oracle`` on a scene without an exact renderer.
    """
    from schemas.pipeline import PipelineConfig

    from freescale_core.freeviews.rectify_image import ReprojectRectifier
    from freescale_core.freeviews.run import make_render_fn
    from freescale_core.recon.trainer import reconstruct

    log = log or (lambda s: None)
    if fold not in FOLDS:
        raise ValueError(f"unknown fold {fold!r}; expected one of {FOLDS}")
    oracle = None
    if fold == "oracle":
        from freescale_core.scene.oracle import ground_truth_oracle

        oracle = ground_truth_oracle(scene_path)
        if oracle is None:
            raise ValueError(f"scene '{scene.scene_id}': fold 'oracle' needs an exact renderer "
                             "(a procedural scene's scene.json)")
        train_idx, test_idx = scene.split("all")
    else:
        train_idx, test_idx = scene.split(fold)
    train_idx = np.asarray(train_idx, np.int64)
    if np.intersect1d(train_idx, test_idx).size:
        raise LeakError(f"scene '{scene.scene_id}': fold {fold}: held-out views "
                        f"{sorted(set(train_idx) & set(test_idx))} are training views")
    rcfg = PipelineConfig.model_validate({"preset": cfg.recon_preset, "seed": seed}).recon
    rcfg = rcfg.model_copy(update={"threads": cfg.threads} if cfg.threads else {})
    budgets = sorted(set(float(b) for b in cfg.budgets))
    snap_steps = {int(round(b * rcfg.max_iterations)): b for b in budgets if b < 1.0}
    snaps: dict[float, object] = {}

    def on_checkpoint(step, g, info):
        if step in snap_steps:
            snaps[snap_steps[step]] = g
        return None

    every = int(np.gcd.reduce(list(snap_steps))) if snap_steps else 0
    t0 = time.perf_counter()
    res = reconstruct(scene, rcfg, seed, train_idx=train_idx, checkpoint_every=every,
                      on_checkpoint=on_checkpoint if every else None)
    recon_s = time.perf_counter() - t0
    snaps[1.0] = res.gaussians
    bg = res.background  # what its PLY would say (ReconResult.write_ply)
    long = float(max(np.max(scene.cameras.width), np.max(scene.cameras.height)))
    scale = min(1.0, float(cfg.long_side) / long)
    tr_cams, tr_photos, _ = _scene_pixels(scene, train_idx, scale)
    if oracle is not None:
        from freescale_core.scene.family import off_path_poses

        cams = off_path_poses(oracle, int(cfg.oracle_views), seed=seed,
                              width=int(tr_cams.width[0]), height=int(tr_cams.height[0]))
        targets = [np.asarray(oracle.render_camera(cams, j)[0], np.float32) / 255.0
                   for j in range(len(cams))]
        tmasks = [None] * len(cams)
        view_ids = [-1] * len(cams)
        names = [f"offpath_{j:03d}" for j in range(len(cams))]
    else:
        test_idx = _pick(np.asarray(test_idx, np.int64), int(cfg.max_views_per_fold))
        cams, targets, tmasks = _scene_pixels(scene, test_idx, scale)
        view_ids = [int(i) for i in test_idx]
        names = [scene.image_names[int(i)] for i in test_idx]
    rect = ReprojectRectifier(**cfg.reproject)
    samples = []
    for b in budgets:
        g = snaps.get(b)
        if g is None:  # training ended (plateau) before this snapshot
            log(f"{scene.scene_id}/{fold}: no snapshot at budget {b} (training stopped "
                f"at {res.stats.get('iterations')} steps)")
            continue
        render_fn = make_render_fn(g, bg, rcfg.raster_backend)
        cache: dict = {}
        for j in range(len(cams)):
            s = view_pair(render_fn, cams, j, tr_cams, tr_photos, cache, int(cfg.k), rect,
                          targets[j], tmasks[j])
            s.meta.update(pair_id=f"{fold}_b{int(round(b * 100)):03d}_{j:03d}",
                          scene_id=scene.scene_id, fold=fold, budget=b,
                          view_index=view_ids[j], view_name=names[j],
                          source="oracle" if oracle is not None else "heldout")
            samples.append(s)
    facts = {"n_train": int(len(train_idx)), "n_test": int(len(cams)),
             "train_idx": [int(i) for i in train_idx], "test_idx": view_ids,
             "recon_seconds": round(recon_s, 2), "iterations": res.stats.get("iterations"),
             "scale": scale, "budgets": [b for b in budgets if b in snaps]}
    return samples, facts


def make_scene_pairs(scene_path: str | Path, out_root: str | Path, cfg=None, seed: int = 0,
                     scene_id: str | None = None, force: bool = False,
                     log: Callable[[str], None] | None = None) -> list[dict]:
    """Write every fold of one scene under ``out_root/<scene_id>/<fold>/`` (resumable: a
    fold whose ``done.json`` key matches is kept). Returns one summary dict per fold."""
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.fingerprint import input_fingerprint

    cfg = cfg or PairsConfig()
    log = log or (lambda s: None)
    scene_path = Path(scene_path)
    sid = scene_id or scene_path.name
    out_root = Path(out_root)
    scene = None
    out = []
    has_oracle = (scene_path / "scene.json").is_file()
    folds = [f for f in cfg.folds if f != "oracle" or has_oracle]
    listed = (scene_path / "heldout.txt").is_file()
    if listed and "every8" in folds and "ood" in folds:
        folds.remove("ood")  # both would hold out the listed views
    inputs = input_fingerprint(scene_path)
    for fold in folds:
        key = {"config": cfg.model_dump(mode="json"), "fold": fold, "seed": int(seed),
               "scene_id": sid, "inputs": inputs, "code": pairs_code_hash()}
        folder = out_root / sid / fold
        done = folder / "done.json"
        if not force and done.is_file():
            try:
                old = json.loads(done.read_text())
            except (OSError, ValueError):
                old = None
            if old is not None and {k: old.get(k) for k in key} == key:
                log(f"{sid}/{fold}: pairs up to date, kept")
                out.append({"scene_id": sid, "fold": fold, "kept": True, "folder": str(folder)})
                continue
        if scene is None:
            scene = load_scene(scene_path, scene_id=sid,
                               cache_dir=str(out_root / ".cache"))
        t0 = time.perf_counter()
        samples, facts = make_fold_pairs(scene, fold, cfg, seed, scene_path, log)
        key["facts"] = facts
        write_pair_folder(folder, samples, key)
        ps = [s.meta["psnr_render"] for s in samples]
        log(f"{sid}/{fold}: {len(samples)} pairs, render PSNR median "
            f"{np.median(ps) if ps else float('nan'):.2f} dB, {time.perf_counter() - t0:.1f} s")
        out.append({"scene_id": sid, "fold": fold, "kept": False, "folder": str(folder),
                    "n_pairs": len(samples), "seconds": round(time.perf_counter() - t0, 2),
                    **facts})
    return out
