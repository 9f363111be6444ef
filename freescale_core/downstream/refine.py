"""Free views as pseudo ground truth for a per-scene 3D Gaussian reconstruction (METHOD.md
"Downstream uses", 3DGS refinement), measured on held-out views. Pure Python, no Prefect
(``flows/refine_3dgs.py`` orders it; docs/REFINE.md has the numbers).

Per scene version of a store published with ``recon_split=ood`` (free views made from a
reconstruction of the first 70% of the capture; the last 30% are ``heldout`` rows):

* :func:`load_refine_scene` reads the training views, free views (with their WIoU to the
  training views and BRISQUE), held-out views and, for procedural scenes, the oracle;
* :class:`PseudoViewPool` is the trainer's view source: the captured views plus free views
  that join the training set on a schedule (every ``interval`` steps the next ``per_step``
  not-yet-used ids of a ranking, each once, by id, with its own weight);
* :func:`run_arm` trains one arm (baseline or a refined variant) with the reconstruction
  trainer (:func:`freescale_core.recon.trainer.train`) and scores it on the held-out views;
* :func:`refine_scene` runs the arms x seeds of a scene, writing each finished arm atomically
  under ``STORE/scenes/<id>/refine/<version>/<config hash>/<arm>/seed<k>/`` and skipping arms
  already there (resume).

The free-view loss is ``alpha_fv * (L1 + (1 - SSIM))`` = ``2 alpha_fv * (0.5 L1 + 0.5 (1 -
SSIM))``: a :class:`View` with ``weight = 2 alpha_fv`` and ``lambda_ssim = 0.5``.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from freescale_core.errors import StoreError
from freescale_core.geometry.cameras import Cameras
from freescale_core.recon.views import CapturedViews, View, ViewCamera
from freescale_core.scene.images import psnr_u8, resize_area as _resize
from schemas.refine import FIXED_ARMS, RefineConfig

REFINE_DIR = "refine"
METRICS = "metrics.json"


# =========================================================================== the scene
@dataclass
class RefineScene:
    """What a comparison needs from one published scene version.

    Attributes:
        fvs: the :class:`~freescale_core.store.reader.FreeViewSet`.
        train_ids: ``[T]`` view ids of the training views (capture order).
        free_ids, free_wiou, free_brisque: ``[F]`` stored free views, their WIoU to the
            training views (``RefineConfig.wiou_reduce``) and BRISQUE/100.
        heldout_ids, heldout_cams, heldout_paths: held-out views (never trained on).
        offpath_cams: candidate poses no arm trains on (procedural oracle scoring).
        oracle: the procedural scene's exact renderer, or None.
    """

    fvs: object
    train_ids: np.ndarray
    free_ids: np.ndarray
    free_wiou: np.ndarray
    free_brisque: np.ndarray
    heldout_ids: np.ndarray
    heldout_cams: Cameras | None
    heldout_paths: list
    offpath_cams: Cameras | None = None
    oracle: object = None
    free_gt_psnr: np.ndarray | None = None

    @property
    def scene_id(self) -> str:
        return self.fvs.scene_id


def _table_cameras(t) -> Cameras:
    from freescale_core.store.layout import world_from_cam_column

    col = lambda k, dt: np.asarray(t.column(k).to_numpy(zero_copy_only=False), dt)  # noqa: E731
    return Cameras(world_from_cam_column(t), col("fx", np.float64), col("fy", np.float64),
                   col("cx", np.float64), col("cy", np.float64), col("width", np.int64),
                   col("height", np.int64))


def free_view_wiou(fvs, free_ids: np.ndarray, train_ids: np.ndarray, reduce: str = "max"
                   ) -> np.ndarray:
    """WIoU of each free view to the training views: ``max`` = views.parquet
    ``wiou_to_train`` when stored (else the max over graph edges); ``mean`` = mean over the
    training views of the graph edges (0 where no edge)."""
    t = fvs.views
    if reduce == "max" and "wiou_to_train" in t.column_names:
        vid = t.column("view_id").to_numpy()
        w = np.asarray(t.column("wiou_to_train").to_numpy(zero_copy_only=False), np.float64)
        by_id = dict(zip(vid.tolist(), w.tolist()))
        out = np.array([by_id.get(int(i), np.nan) for i in free_ids], np.float64)
        if not np.isnan(out).any():
            return out
    src, dst, w = fvs.graph(dataset_only=True)
    tr = set(int(i) for i in train_ids)
    acc = {int(i): [] for i in free_ids}
    for a, b, x in zip(src.tolist(), dst.tolist(), w.tolist()):
        if a in acc and b in tr:
            acc[a].append(x)
        elif b in acc and a in tr:
            acc[b].append(x)
    if reduce == "max":
        return np.array([max(acc[int(i)], default=0.0) for i in free_ids], np.float64)
    return np.array([sum(acc[int(i)]) / max(len(train_ids), 1) for i in free_ids], np.float64)


def load_refine_scene(fvs, cfg: RefineConfig, source: str | Path | None = None) -> RefineScene:
    """Read a published version for a comparison.

    Args:
        fvs: :class:`~freescale_core.store.reader.FreeViewSet`.
        source: the scene folder the version was made from (the oracle lives there for
            procedural scenes); default: the store's status record of the scene.
    Raises:
        StoreError: the version has no held-out views (not made with ``recon_split=ood`` or
            ``every8``), or a held-out photo is missing.
    """
    import pyarrow.compute as pc

    from freescale_core.scene.oracle import ground_truth_oracle

    sid = fvs.scene_id
    v = fvs.dataset_views()
    train_ids = v.view_id[~v.is_free]
    free_ids = v.view_id[v.is_free]
    free_b = v.brisque[v.is_free]
    wiou = free_view_wiou(fvs, free_ids, train_ids, cfg.wiou_reduce)
    t = fvs.views
    ho = t.filter(pc.equal(t.column("disposition"), "heldout"))
    if ho.num_rows == 0:
        raise StoreError(f"scene {sid!r}: {fvs.version_dir / 'views.parquet'} has no held-out "
                         "views; publish the scene with --set recon_split=ood to refine it")
    names = ho.column("name").to_pylist()
    paths = [fvs.version_dir / "images" / n for n in names]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise StoreError(f"scene {sid!r}: held-out photos missing: {missing[:3]}")
    if source is None:
        from freescale_core.store.store import Store

        store_root = fvs.version_dir.parent.parent.parent
        source = Store(store_root).read_status(sid).get("source")
    oracle = ground_truth_oracle(source) if source else None
    off = None
    if oracle is not None and cfg.oracle_views > 0:
        cand = t.filter(pc.is_in(t.column("disposition"),
                                 value_set=__import__("pyarrow").array(["suppressed",
                                                                        "rejected"])))
        if cand.num_rows:
            k = np.unique(np.linspace(0, cand.num_rows - 1,
                                      min(cfg.oracle_views, cand.num_rows)).astype(int))
            off = _table_cameras(cand).subset(k)
    gt = np.full(len(free_ids), np.nan)
    if "gt_psnr" in t.column_names:  # sample scenes: each free view's PSNR against truth
        by_id = dict(zip(t.column("view_id").to_pylist(), t.column("gt_psnr").to_pylist()))
        gt = np.array([np.nan if by_id.get(int(i)) is None else by_id[int(i)]
                       for i in free_ids], np.float64)
    return RefineScene(fvs, train_ids, free_ids, wiou, free_b,
                       np.asarray(ho.column("view_id").to_numpy(), np.int64),
                       _table_cameras(ho), paths, off, oracle, gt)


def training_data(rs: RefineScene, recon_cfg):
    """The trainer's :class:`~freescale_core.recon.trainer.TrainingData` from the published
    training views, at the resolution the reconstruction's resolution rule picks."""
    from freescale_core.recon.trainer import TrainingData, choose_resolution, scene_extent

    fvs = rs.fvs
    ids, cams_native = fvs.cameras("train")
    imgs = [fvs.rgb(int(i)) for i in ids]
    probe = [imgs[int(k)] for k in np.linspace(0, len(imgs) - 1, min(3, len(imgs))).astype(int)]
    scale, why = choose_resolution(cams_native.width, cams_native.height, recon_cfg, probe)
    cams = cams_native.scaled(scale)
    images = [torch.from_numpy(np.ascontiguousarray(_resize(im, cams.width[j], cams.height[j])))
              for j, im in enumerate(imgs)]
    xyz, rgb = fvs.points()
    return TrainingData(rs.scene_id, fvs.version_dir, cams, images, xyz, rgb,
                        scene_extent(cams_native, xyz), scale, ids, {"train_resolution": why})


# =========================================================================== the schedule
def rank_free_views(rs: RefineScene, order: str, seed: int) -> list[int]:
    """Free-view ids in the order they join: ``wiou`` = lowest WIoU to the training views
    first (ties by id), ``outward`` = highest first (the ring nearest the captured path
    first), ``random`` = a permutation seeded by ``seed`` (its own generator: the
    trainer's random state is untouched)."""
    ids = rs.free_ids.astype(np.int64)
    if order == "wiou":
        w = np.nan_to_num(rs.free_wiou, nan=np.inf)
        return [int(ids[k]) for k in np.lexsort((ids, w))]
    if order == "outward":  # the nearest ring first: highest WIoU to the training views
        w = np.nan_to_num(rs.free_wiou, nan=-np.inf)
        return [int(ids[k]) for k in np.lexsort((ids, -w))]
    if order == "random":
        rng = np.random.default_rng([int(seed), 0x5EED])
        return [int(i) for i in ids[rng.permutation(len(ids))]]
    raise ValueError(f"unknown free-view order {order!r} (expected 'wiou', 'outward' or "
                     "'random')")


@dataclass
class Added:
    """One free view that joined the training set."""

    step: int
    view_id: int
    weight: float
    alpha: float
    info: dict = field(default_factory=dict)  # fixed arms: coverage, confidence, truth PSNR


class PseudoViewPool:
    """View source: the captured views plus free views that join on a schedule.

    At each step in ``schedule`` (once per step, whatever the number of calls) the next
    ``per_step`` ids of ``ranking`` not used yet join the pool, each with its own
    :class:`View` from ``make_view(view_id)`` (weight and all). Views are drawn as the
    captured source draws them: a fresh seeded permutation of the whole pool per epoch (views
    that join mid-epoch are in the next permutation), from the trainer's generator.

    ``added`` records every join (step, id, weight).
    """

    def __init__(self, captured: CapturedViews, ranking: Sequence[int], schedule: Sequence[int],
                 per_step: int, make_view: Callable[[int], View],
                 max_views: int | None = None):
        self.captured = captured
        self.ranking = [int(i) for i in ranking]
        if len(set(self.ranking)) != len(self.ranking):
            raise ValueError("PseudoViewPool: ranking lists a view id twice")
        self.schedule = sorted(set(int(s) for s in schedule))
        self.per_step = int(per_step)
        self.max_views = max_views
        self.make_view = make_view
        self.pseudo: list[View] = []
        self.used: set[int] = set()
        self.fired: set[int] = set()
        self.added: list[Added] = []
        self._order = np.zeros(0, np.int64)
        self.state = None  # the trainer's TrainState (bind): the model being trained

    def bind(self, state) -> None:
        """Called by the trainer before its first step (``make_view`` may render from
        ``self.state.params``: the progressive arm)."""
        self.state = state

    def _join(self, step: int) -> None:
        self.fired.add(step)
        room = self.per_step
        if self.max_views is not None:
            room = min(room, self.max_views - len(self.used))
        if room <= 0:
            return
        take = [i for i in self.ranking if i not in self.used][:room]  # by id, never by position
        for vid in take:
            v = self.make_view(vid)
            v.index, v.kind = vid, "pseudo"
            self.pseudo.append(v)
            self.used.add(vid)
            self.added.append(Added(step, vid, float(v.weight),
                                    float(getattr(v, "alpha", v.weight / 2.0)),
                                    dict(getattr(v, "info", {}))))

    def next(self, step: int, rng: np.random.Generator) -> View:
        if step in self.schedule and step not in self.fired:
            self._join(step)
        if len(self._order) == 0:
            self._order = rng.permutation(len(self.captured) + len(self.pseudo))
        j, self._order = int(self._order[0]), self._order[1:]
        n = len(self.captured)
        return self.captured.view(j) if j < n else self.pseudo[j - n]


# =========================================================================== one arm
@dataclass
class ArmResult:
    gaussians: object
    metrics: dict = field(default_factory=dict)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # trained on; saved in its PLY


def store_background(rs: "RefineScene", rc) -> tuple[float, float, float]:
    """The colour the store's reconstruction was trained on: its PLY's
    (``scene.ply.read_background``), else the configured ``rc.background``."""
    from freescale_core.scene.ply import read_background

    ply = getattr(rs.fvs, "gaussians_ply", None)
    default = tuple(float(x) for x in rc.background)
    return default if ply is None else read_background(ply, default, rs.scene_id)


def free_camera(rs: RefineScene, vid: int, train_fx: float) -> ViewCamera:
    """Camera of free view ``vid`` at the training views' pixel density: scaled so its focal
    length is ``train_fx`` (the median training focal length at the training resolution).
    Free views are stored at their own render size (the reconstruction's training size times
    ``freeview.render_scale``), not at the published photos' size."""
    v = rs.fvs.dataset_views()
    r = int(np.flatnonzero(v.view_id == vid)[0])
    c = v.cameras.subset([r])
    c = c.scaled(float(train_fx) / float(c.fx[0]))
    return ViewCamera(c.world_from_cam[0], float(c.fx[0]), float(c.fy[0]), float(c.cx[0]),
                      float(c.cy[0]), int(c.width[0]), int(c.height[0]))


def pseudo_image(rs: RefineScene, arm: str, vid: int, cam: ViewCamera, store_gaussians=None,
                 background=(0.0, 0.0, 0.0), backend: str = "auto") -> np.ndarray:
    """``[h, w, 3]`` uint8 pseudo ground truth of free view ``vid`` at ``cam`` (training
    resolution): the stored (rectified) image (``wiou``, ``random``), the raw render of the
    store's reconstruction (``raw``) or the oracle's true image (``oracle``)."""
    if arm in ("wiou", "random"):
        img = rs.fvs.rgb(vid)
        return _resize(img, cam.width, cam.height)
    if arm == "raw":
        from freescale_core.raster import render_gaussians

        rgb, _, _ = render_gaussians(store_gaussians, cam.world_from_cam, cam.fx, cam.fy,
                                     cam.cx, cam.cy, cam.width, cam.height,
                                     background=tuple(background), backend=backend)
        return np.floor(np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
    if arm == "oracle":
        if rs.oracle is None:
            raise ValueError(f"scene {rs.scene_id!r}: the oracle arm needs a procedural scene")
        # Render at the native free-view size, then area-downscale like the training photos.
        v = rs.fvs.dataset_views()
        r = int(np.flatnonzero(v.view_id == vid)[0])
        img, _ = rs.oracle.render_camera(v.cameras, r)
        return _resize(img, cam.width, cam.height)
    raise ValueError(f"arm {arm!r} has no pseudo views")


def _score(gaussians, cams: Cameras, images: list, bg, backend) -> dict:
    from freescale_core.recon.trainer import _evaluate_views

    ev = _evaluate_views(gaussians, cams, images, bg, backend)
    return {"psnr": [float(x) for x in ev["psnr"]], "ssim": [float(x) for x in ev["ssim"]],
            "psnr_mean": ev["psnr_mean"], "ssim_mean": ev["ssim_mean"]}


def heldout_targets(rs: RefineScene, scale: float) -> tuple[Cameras, list]:
    """Held-out cameras and photos at the training scale."""
    from freescale_core.scene.scene import read_rgb

    cams = rs.heldout_cams.scaled(scale)
    imgs = [_resize(read_rgb(p, rs.scene_id), cams.width[j], cams.height[j])
            for j, p in enumerate(rs.heldout_paths)]
    return cams, imgs


def offpath_targets(rs: RefineScene, scale: float) -> tuple[Cameras | None, list]:
    """Oracle truth at the off-path poses, rendered natively then area-downscaled."""
    if rs.oracle is None or rs.offpath_cams is None or not len(rs.offpath_cams):
        return None, []
    cams = rs.offpath_cams.scaled(scale)
    imgs = [_resize(rs.oracle.render_camera(rs.offpath_cams, j)[0], cams.width[j],
                    cams.height[j]) for j in range(len(cams))]
    return cams, imgs


def run_arm(rs: RefineScene, data, cfg: RefineConfig, arm: str, seed: int,
            targets: dict | None = None, store_gaussians=None, steps: int | None = None,
            fixer=None) -> ArmResult:
    """Train one arm from scratch with the reconstruction trainer and score it.

    Args:
        rs: the scene. data: its :func:`training_data` (shared by every arm: same images,
            same resolution).
        arm: one of :data:`schemas.refine.ARM_KINDS` (``kind@rule`` for a weight rule).
        seed: the trainer's seed (same for every arm of a comparison).
        targets: ``{"heldout": (cams, images), "offpath": (cams, images)}`` (computed once
            per scene; default: computed here).
        store_gaussians: the store's reconstruction (``raw`` and ``fixed`` arms).
        steps: the step budget (``baseline+time``; default ``cfg.recon.max_iterations``).
        fixer: a :class:`~freescale_core.downstream.refine_fix.SceneFixer` (fixed arms and
            ``post_fix``; default: built from ``cfg.fixer``).
    Returns:
        :class:`ArmResult` with ``metrics``: ``heldout`` / ``offpath`` per-view PSNR/SSIM and
        means, ``train_seconds``, ``cpu_seconds``, ``iterations``, ``added`` (step, view id,
        weight, alpha, fixer info), and with ``post_fix`` ``heldout_post``.
    """
    from freescale_core.recon.trainer import train

    rc = cfg.recon
    if steps is not None and steps != rc.max_iterations:
        rc = rc.model_copy(update={"max_iterations": int(steps), "min_iterations": int(steps)})
    bg = store_background(rs, rc)  # renders of the store's reconstruction
    if targets is None:
        targets = {"heldout": heldout_targets(rs, data.scale),
                   "offpath": offpath_targets(rs, data.scale)}
    captured = CapturedViews(data)
    kind, _, rule = arm.partition("@")
    rule = rule or cfg.weight_rule
    if fixer is None and (kind in FIXED_ARMS or cfg.post_fix):
        from freescale_core.downstream.refine_fix import SceneFixer

        fixer = SceneFixer(data, cfg.fixer, bg, rc.raster_backend)
    if kind.startswith("baseline"):
        source = captured
        pool = None
    else:
        order = {"random": "random", "progressive": "outward"}.get(kind, "wiou")
        ranking = rank_free_views(rs, order, seed)
        brisque = dict(zip(rs.free_ids.tolist(), rs.free_brisque.tolist()))
        train_fx = float(np.median(data.cams.fx))
        box: dict = {}

        def make_view(vid: int) -> View:
            cam = free_camera(rs, vid, train_fx)
            a = cfg.alpha(brisque.get(vid, float("nan")), rule)
            mask, info = None, {}
            if kind in FIXED_ARMS:
                from freescale_core.downstream.refine_fix import params_gaussians

                live = kind == "progressive"
                g = params_gaussians(box["pool"].state) if live else store_gaussians
                r = fixer.fix(g, cam, cache_key=None if live else 0)
                img = r["image"]
                w = r["confidence"] * r["observed"]
                if kind != "fixed":
                    mask = torch.from_numpy(np.ascontiguousarray(w, np.float32))
                info = {"coverage": r["coverage"], "confidence": float(r["confidence"].mean()),
                        "weight_mean": float(w.mean())}
                if rs.oracle is not None:
                    truth = pseudo_image(rs, "oracle", vid, cam)
                    info["pseudo_gt_psnr"] = psnr_u8(img, truth)
                    info["render_gt_psnr"] = psnr_u8(r["render"], truth)
            else:
                img = pseudo_image(rs, kind, vid, cam, store_gaussians, bg, rc.raster_backend)
            v = View(torch.from_numpy(np.ascontiguousarray(img)), cam, weight=2.0 * a,
                     mask=mask, lambda_ssim=0.5)
            v.alpha = a
            v.info = info
            return v

        pool = PseudoViewPool(captured, ranking, cfg.schedule(), cfg.per_step, make_view,
                              cfg.max_free_views)
        box["pool"] = pool
        source = pool
    fix_s0 = fixer.seconds if fixer is not None else 0.0
    t0, c0 = time.perf_counter(), time.process_time()
    res = train(data, rc, seed, view_source=source)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    g = res.gaussians
    bg = res.background  # the refined model's (learned when rc.background_lr is set)
    hc, hi = targets["heldout"]
    gt = {} if rs.free_gt_psnr is None else dict(zip(rs.free_ids.tolist(),
                                                      rs.free_gt_psnr.tolist()))
    added = [vars(a) | {"gt_psnr": gt.get(a.view_id, float("nan"))}
             for a in (pool.added if pool else [])]
    m = {"scene": rs.scene_id, "arm": arm, "seed": int(seed), "weight_rule":
         None if kind.startswith("baseline") else rule,
         "heldout_view_ids": rs.heldout_ids.tolist(),
         "heldout": _score(g, hc, hi, bg, rc.raster_backend),
         "train_seconds": float(res.stats["train_seconds"]), "wall_seconds": wall,
         "cpu_seconds": cpu,
         "fixer_seconds": (fixer.seconds - fix_s0) if fixer is not None else 0.0,
         "iterations": int(res.stats["iterations"]), "n_gaussians": len(g),
         "train_resolution": res.stats["train_resolution"], "n_train_views": len(data.images),
         "recon_train_psnr": res.stats["recon_train_psnr"],
         "added": added,
         "schedule": cfg.schedule() if pool else []}
    oc, oi = targets.get("offpath") or (None, [])
    if oc is not None:
        m["offpath"] = _score(g, oc, oi, bg, rc.raster_backend)
    if cfg.post_fix:
        m["heldout_post"] = post_fix_scores(fixer, g, hc, hi)
    return ArmResult(g, m, bg)


def post_fix_scores(fixer, g, cams: Cameras, images: list) -> dict:
    """PSNR / SSIM of the fixer's output on ``g``'s renders at ``cams`` (held-out poses)
    against ``images``; the references are the nearest *training* photos."""
    from freescale_core.recon.losses import masked_psnr_ssim

    t0 = time.perf_counter()
    ps, ss = [], []
    for j in range(len(cams)):
        cam = ViewCamera(cams.world_from_cam[j], float(cams.fx[j]), float(cams.fy[j]),
                         float(cams.cx[j]), float(cams.cy[j]), int(cams.width[j]),
                         int(cams.height[j]))
        r = fixer.fix(g, cam, cache_key=id(g))
        p, s_ = masked_psnr_ssim(torch.from_numpy(r["image"]).double() / 255.0,
                                 torch.from_numpy(np.asarray(images[j])).double() / 255.0, None)
        ps.append(float(p))
        ss.append(float(s_))
    fixer.forget(id(g))
    return {"psnr": ps, "ssim": ss, "psnr_mean": float(np.mean(ps)) if ps else float("nan"),
            "ssim_mean": float(np.mean(ss)) if ss else float("nan"),
            "seconds": time.perf_counter() - t0}


# =========================================================================== store output
def refine_key(cfg: RefineConfig) -> str:
    """Hash of everything an arm's result depends on except the arm and seed lists (adding an
    arm or a seed reuses finished ones), the code included."""
    from freescale_core.store.store import config_hash

    from freescale_core.codekey import code_key

    # and the code an arm's result reaches (freescale_core.codekey): an edit re-runs the arms
    d = cfg.model_dump(mode="json", exclude={"arms", "seeds", "weight_rule"})
    if d.get("fixer") or cfg.post_fix or set(FIXED_ARMS) & {a.partition("@")[0]
                                                             for a in cfg.arms}:
        from freescale_core.freeviews.rectify_image import shipped_checkpoint

        d["fixer"] = _file_sha256(Path(cfg.fixer or shipped_checkpoint()))  # content, not path
    return config_hash({**d, "code": code_key((__name__, "freescale_core.downstream.refine_fix"))})


def _file_sha256(p: Path) -> str:
    import hashlib

    try:
        return hashlib.sha256(p.read_bytes()).hexdigest()
    except OSError as e:
        raise StoreError(f"fixer checkpoint {p}: cannot be read ({e.strerror or e})") from None


def refine_root(fvs, cfg: RefineConfig) -> Path:
    """``STORE/scenes/<id>/refine/<version>/<key>/``: beside the published version (which is
    never modified), keyed by the version it read and the config."""
    return fvs.version_dir.parent / REFINE_DIR / fvs.version / refine_key(cfg)


def arm_dir(root: Path, arm: str, seed: int) -> Path:
    return Path(root) / arm / f"seed{int(seed)}"


def arm_done(root: Path, arm: str, seed: int) -> dict | None:
    """The finished arm's metrics, or None (a folder appears only when complete)."""
    p = arm_dir(root, arm, seed) / METRICS
    if not p.is_file():
        return None
    try:
        return json.loads(p.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def write_arm(root: Path, result: ArmResult) -> Path:
    """Publish one arm atomically: build ``gaussians.ply``, ``heldout.parquet`` and
    ``metrics.json`` in a staging folder, then rename it into place (a crash leaves either
    no folder or a complete one)."""
    import pyarrow as pa

    from freescale_core.scene.ply import write_ply
    from freescale_core.store.store import write_json_atomic, write_parquet_atomic

    m = result.metrics
    final = arm_dir(root, m["arm"], m["seed"])
    final.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".staging-{final.name}-", dir=final.parent))
    try:
        write_ply(staging / "gaussians.ply", result.gaussians, background=result.background)
        h = m["heldout"]
        write_parquet_atomic(staging / "heldout.parquet", pa.table({
            "view_id": pa.array(m["heldout_view_ids"], pa.int64()),
            "psnr": pa.array(h["psnr"], pa.float64()), "ssim": pa.array(h["ssim"], pa.float64())}))
        write_json_atomic(staging / METRICS, m)
        if final.exists():  # a finished arm of a concurrent run: keep it
            shutil.rmtree(staging, ignore_errors=True)
            return final
        os.rename(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return final


def _warm_up(data, cfg: RefineConfig) -> None:
    """A few discarded steps before the first timed arm, so the rasterizer's one-off JIT
    compilation is not billed to whichever arm runs first."""
    from freescale_core.recon.trainer import train

    rc = cfg.recon.model_copy(update={"max_iterations": 3, "min_iterations": 3})
    train(data, rc, 0)


def refine_scene(fvs, cfg: RefineConfig, source: str | Path | None = None,
                 log: Callable[[str], None] = print,
                 after_arm: Callable[[dict], None] | None = None,
                 compute: bool = True) -> dict:
    """Run every arm x seed of ``cfg`` on one published scene version; finished arms on disk
    are reused, not recomputed.

    Returns:
        ``{"scene", "version", "root", "arms": {arm: {seed: metrics}}, "computed": [...],
        "reused": [...], "skipped": [...]}`` and writes ``summary.json`` in the root.
        With ``compute=False`` nothing is trained or written: finished arms only, and
        ``"missing"`` lists the others.
    """
    from freescale_core.scene.ply import read_ply
    from freescale_core.store.store import write_json_atomic

    rs = load_refine_scene(fvs, cfg, source)
    root = refine_root(fvs, cfg)
    out = {"scene": rs.scene_id, "version": fvs.version, "root": str(root), "arms": {},
           "computed": [], "reused": [], "skipped": [], "n_free_views": int(len(rs.free_ids)),
           "n_train_views": int(len(rs.train_ids)), "n_heldout_views": int(len(rs.heldout_ids))}
    todo = []
    for arm in cfg.arm_names():
        if arm.startswith("oracle") and rs.oracle is None:
            out["skipped"].append(arm)
            continue
        for s in cfg.seeds:
            done = arm_done(root, arm, s)
            if done is not None:
                out["arms"].setdefault(arm, {})[str(s)] = done
                out["reused"].append(f"{arm}/seed{s}")
            else:
                todo.append((arm, s))
    if not compute:  # read-only: what is finished
        out["missing"] = [f"{a}/seed{s}" for a, s in todo]
        return out
    if todo:
        data = training_data(rs, cfg.recon)
        targets = {"heldout": heldout_targets(rs, data.scale),
                   "offpath": offpath_targets(rs, data.scale)}
        store_g = None
        kinds = {a.partition("@")[0] for a, _ in todo}
        if kinds & {"raw", "fixed", "fixed+conf"}:
            if fvs.gaussians_ply is None:
                raise StoreError(f"scene {rs.scene_id!r}: the raw and fixed arms re-render the "
                                 f"store's reconstruction, but {fvs.version_dir}/gaussians.ply "
                                 "is missing")
            store_g = read_ply(fvs.gaussians_ply, rs.scene_id)
        fixer = None
        if kinds & set(FIXED_ARMS) or cfg.post_fix:
            from freescale_core.downstream.refine_fix import SceneFixer

            fixer = SceneFixer(data, cfg.fixer, store_background(rs, cfg.recon),
                               cfg.recon.raster_backend)
        # baseline+time runs last: its budget is read from the refined arms' CPU seconds
        todo.sort(key=lambda t: t[0] == "baseline+time")
        _warm_up(data, cfg)
        for arm, s in todo:
            steps = None
            if arm == "baseline+time":
                steps = time_matched_steps(cfg, out["arms"], s)
                if steps is None:
                    out["skipped"].append(f"{arm}/seed{s}")
                    log(f"[refine] {rs.scene_id}: baseline+time seed {s} skipped: it needs "
                        "the baseline and a refined arm of the same seed")
                    continue
            log(f"[refine] {rs.scene_id}: {arm} seed {s} ...")
            r = run_arm(rs, data, cfg, arm, s, targets, store_g, steps=steps, fixer=fixer)
            write_arm(root, r)
            out["arms"].setdefault(arm, {})[str(s)] = r.metrics
            out["computed"].append(f"{arm}/seed{s}")
            log(f"[refine] {rs.scene_id}: {arm} seed {s}: held-out PSNR "
                f"{r.metrics['heldout']['psnr_mean']:.2f} dB in {r.metrics['train_seconds']:.0f} s")
            if after_arm is not None:
                after_arm(r.metrics)
    write_json_atomic(root / "config.json", cfg.model_dump(mode="json"))
    write_json_atomic(root / "summary.json", summarize_scene(out))
    return out


def time_matched_steps(cfg: RefineConfig, arms: dict, seed: int) -> int | None:
    """Steps of ``baseline+time`` at ``seed``: ``max_iterations`` x the slowest refined arm's
    CPU seconds / the baseline's (same seed), at least ``max_iterations``; None when the
    baseline or every refined arm of that seed is missing. CPU seconds (the process's, not
    the wall clock) so a busy machine does not hand the arm a budget it did not earn."""
    s = str(seed)
    base = arms.get("baseline", {}).get(s)
    refined = [by[s] for a, by in arms.items()
               if not a.startswith("baseline") and s in by]
    if base is None or not refined:
        return None
    key = "cpu_seconds" if all("cpu_seconds" in m for m in [base, *refined]) else "train_seconds"
    ratio = max(m[key] for m in refined) / max(base[key], 1e-9)
    n = cfg.recon.max_iterations
    return max(n, int(round(n * ratio)))


# =========================================================================== summaries
def summarize_scene(out: dict) -> dict:
    """Per arm: mean held-out PSNR/SSIM over seeds, delta to the baseline per seed (mean,
    std), train seconds and overhead vs the baseline."""
    arms = out["arms"]
    base = arms.get("baseline", {})
    rows = {}
    for arm, by_seed in arms.items():
        seeds = sorted(by_seed, key=int)
        p = [by_seed[s]["heldout"]["psnr_mean"] for s in seeds]
        q = [by_seed[s]["heldout"]["ssim_mean"] for s in seeds]
        t = [by_seed[s]["train_seconds"] for s in seeds]
        r = {"seeds": [int(s) for s in seeds], "psnr": float(np.mean(p)),
             "ssim": float(np.mean(q)), "train_seconds": float(np.median(t)),
             "n_added": float(np.mean([len(by_seed[s].get("added", [])) for s in seeds]))}
        gts = [a.get("gt_psnr", np.nan) for s in seeds for a in by_seed[s].get("added", [])]
        if gts and np.isfinite(gts).any():
            r["added_gt_psnr"] = float(np.nanmean(gts))
        if all("heldout_post" in by_seed[s] for s in seeds):
            r["post_psnr"] = float(np.mean([by_seed[s]["heldout_post"]["psnr_mean"]
                                            for s in seeds]))
            r["post_ssim"] = float(np.mean([by_seed[s]["heldout_post"]["ssim_mean"]
                                            for s in seeds]))
        r["iterations"] = float(np.mean([by_seed[s]["iterations"] for s in seeds]))
        if all("offpath" in by_seed[s] for s in seeds):
            r["offpath_psnr"] = float(np.mean([by_seed[s]["offpath"]["psnr_mean"]
                                               for s in seeds]))
        common = [s for s in seeds if s in base]
        if arm != "baseline" and common:
            d = [by_seed[s]["heldout"]["psnr_mean"] - base[s]["heldout"]["psnr_mean"]
                 for s in common]
            ds = [by_seed[s]["heldout"]["ssim_mean"] - base[s]["heldout"]["ssim_mean"]
                  for s in common]
            ov = [by_seed[s]["train_seconds"] / base[s]["train_seconds"] - 1 for s in common]
            r.update({"base_psnr": float(np.mean([base[s]["heldout"]["psnr_mean"]
                                                  for s in common])),
                      "base_ssim": float(np.mean([base[s]["heldout"]["ssim_mean"]
                                                  for s in common])),
                      "arm_psnr": float(np.mean([by_seed[s]["heldout"]["psnr_mean"]
                                                 for s in common])),
                      "dpsnr": float(np.mean(d)), "dpsnr_std": float(np.std(d)),
                      "dssim": float(np.mean(ds)), "overhead": float(np.median(ov))})
            if all("cpu_seconds" in by_seed[s] and "cpu_seconds" in base[s] for s in common):
                r["cpu_overhead"] = float(np.median(
                    [by_seed[s]["cpu_seconds"] / base[s]["cpu_seconds"] - 1 for s in common]))
            bt = arms.get("baseline+time", {})
            ct = [s for s in common if s in bt]
            if arm != "baseline+time" and ct:
                d2 = [by_seed[s]["heldout"]["psnr_mean"] - bt[s]["heldout"]["psnr_mean"]
                      for s in ct]
                r.update({"dpsnr_time": float(np.mean(d2)), "dpsnr_time_std": float(np.std(d2)),
                          "dssim_time": float(np.mean(
                              [by_seed[s]["heldout"]["ssim_mean"] - bt[s]["heldout"]["ssim_mean"]
                               for s in ct]))})
            if "offpath_psnr" in r and all("offpath" in base[s] for s in common):
                r["doffpath_psnr"] = float(np.mean(
                    [by_seed[s]["offpath"]["psnr_mean"] - base[s]["offpath"]["psnr_mean"]
                     for s in common]))
        rows[arm] = r
    return {k: v for k, v in out.items() if k != "arms"} | {"summary": rows}
