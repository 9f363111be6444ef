"""The trainer's input: views loaded once at the chosen resolution (:class:`TrainingData`,
:func:`prepare`), the sparse points a split may start from, and the initial parameters."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
import torch

from freescale_core.errors import DegenerateSceneError
from freescale_core.geometry.cameras import Cameras
from freescale_core.recon.bounds import SceneBounds
from freescale_core.recon.sizing import choose_resolution, scene_extent
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.images import resize_area as _resize
from freescale_core.scene.scene import Scene
from schemas.recon import ReconConfig



# =========================================================================== helpers
def _init_params(scene, cfg: ReconConfig, budget: int,
                 rng: np.random.Generator) -> tuple[dict[str, torch.Tensor], str]:
    """``scene``: anything with ``scene_id``, ``root``, ``points_xyz``, ``points_rgb``."""
    pts, rgb = scene.points_xyz, scene.points_rgb
    finite = np.all(np.isfinite(pts), axis=1)
    pts, rgb = pts[finite], rgb[finite]
    if len(scene.points_xyz) == 0:  # instant-ngp / Blender: random points in the view volume
        from freescale_core.scene.init_points import random_init_points

        pts, rgb, reason = random_init_points(scene, min(budget, cfg.random_init_points), rng)
    elif len(pts) < 4:  # points, but (almost) none usable: a broken SfM model
        raise DegenerateSceneError(scene.scene_id, f"{len(pts)} finite sparse points; "
                                   "reconstruction needs at least 4 to initialise", scene.root)
    else:
        reason = f"{len(pts)} sparse points"
    if len(pts) > budget:
        keep = np.sort(rng.choice(len(pts), size=budget, replace=False))
        pts, rgb = pts[keep], rgb[keep]
        reason += f", randomly subsampled to the budget {budget}"
    g = Gaussians.from_points(pts, rgb.astype(np.float64) / 255.0, sh_degree=cfg.sh_degree,
                              opacity=cfg.opacity_init)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    params = {"means": t(g.means), "log_scales": t(g.log_scales), "quats_wxyz": t(g.quats_wxyz),
              "opacity_logits": t(g.opacity_logits), "sh_dc": t(g.sh[:, :1]),
              "sh_rest": t(g.sh[:, 1:])}
    for p in params.values():
        p.requires_grad_(True)
    return params, reason


def _check_finite(params: dict[str, torch.Tensor], scene, step: int) -> None:
    for k, p in params.items():
        bad = ~torch.isfinite(p.data)
        if bool(bad.any()):
            rows = torch.nonzero(bad.reshape(p.shape[0], -1).any(1)).flatten()
            raise DegenerateSceneError(
                scene.scene_id, f"training diverged: {len(rows)} Gaussians have non-finite "
                f"{k} at step {step} (first rows {rows[:5].tolist()})", scene.root)


def _to_gaussians(params: dict[str, torch.Tensor], sh_degree: int) -> Gaussians:
    d = {k: p.detach().float().numpy() for k, p in params.items()}
    q = d["quats_wxyz"] / np.maximum(np.linalg.norm(d["quats_wxyz"], axis=1, keepdims=True), 1e-12)
    k = (sh_degree + 1) ** 2
    sh = np.concatenate([d["sh_dc"], d["sh_rest"]], axis=1)[:, :k]
    return Gaussians(d["means"], d["log_scales"], q, d["opacity_logits"], sh)


# =========================================================================== training data
@dataclass
class TrainingData:
    """What the loop trains on, at the training resolution.

    Attributes:
        scene_id, root: for error messages.
        cams: :class:`Cameras` of the training views, scaled to the training resolution.
        images: ``[H, W, 3]`` uint8 tensors, one per camera.
        points_xyz, points_rgb: sparse points ``[P, 3]`` (float) and ``[P, 3]`` uint8 (init).
        extent: 3DGS ``spatial_lr_scale`` (:func:`scene_extent`).
        scale: training scale relative to the native images.
        view_ids: the scene's camera index of each training view.
        reasons: why the resolution was chosen.
        masks: ``[H, W]`` bool tensors (True = object), one per camera, or None. With
            ``mask_loss`` the loss counts only these pixels (``masked_pixels="ignore"``);
            without it the images are already composited on the background
            (``"background"``) and the masks only restrict the train PSNR.
        n_points_given: the scene's own sparse points (the budget rule counts these); None:
            ``len(points_xyz)``.
        triangulation: what :func:`init_points_for` added (``n_added``, ``seconds``, ...), or
            None when it did not run.
    """

    scene_id: str
    root: object
    cams: Cameras
    images: list
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    extent: float
    scale: float = 1.0
    view_ids: np.ndarray | None = None
    reasons: dict = field(default_factory=dict)
    bounds: SceneBounds | None = None
    extras: dict = field(default_factory=dict)
    masks: list | None = None
    mask_loss: bool = False
    n_points_given: int | None = None
    triangulation: dict | None = None

    @property
    def n_own_points(self) -> int:
        """How many of ``points_xyz`` (the first ones) are the scene's own sparse points."""
        return len(self.points_xyz) if self.n_points_given is None else self.n_points_given

    # the Scene-like face random initialisation reads (scene/init_points.py)
    @property
    def cameras(self) -> Cameras:
        return self.cams

    def load_image(self, i: int) -> np.ndarray:
        """Training view ``i`` as ``[H, W, 3]`` uint8 (at the training resolution, as ``cams``)."""
        img = self.images[i]
        return img.cpu().numpy() if hasattr(img, "cpu") else np.asarray(img)


def prepare(scene: Scene, cfg: ReconConfig, train_idx: Sequence[int] | np.ndarray | None = None
            ) -> TrainingData:
    """Choose the training resolution and load the training views of ``scene``."""
    sid = scene.scene_id
    train = np.arange(len(scene)) if train_idx is None else np.asarray(train_idx, np.int64)
    if len(train) < 1:
        raise DegenerateSceneError(sid, "no training views", scene.root)
    reasons: dict[str, str] = {}
    cams_native = scene.cameras.subset(train)
    probe = [scene.load_image(int(i)) for i in train[np.linspace(0, len(train) - 1,
                                                                   min(3, len(train))).astype(int)]]
    scale, reasons["train_resolution"] = choose_resolution(
        cams_native.width, cams_native.height, cfg, probe)
    cams = cams_native.scaled(scale)
    images = []
    masks = [] if getattr(scene, "has_masks", False) else None
    bg = np.asarray(cfg.background, np.float64) * 255.0
    for j, i in enumerate(train):
        img = _resize(scene.load_image(int(i)), cams.width[j], cams.height[j])
        if masks is not None:
            from freescale_core.scene.io.masks import resize_mask

            m = resize_mask(scene.load_mask(int(i)), int(cams.width[j]), int(cams.height[j]))
            if cfg.masked_pixels == "background":  # the object on the training background
                img = np.where(m[..., None], img, np.rint(bg)).astype(np.uint8)
            masks.append(torch.from_numpy(m))
        images.append(torch.from_numpy(img))
    if masks is not None:
        cover = float(np.mean([float(m.float().mean()) for m in masks]))
        reasons["masks"] = (f"object masks cover {cover:.0%} of the training pixels; outside: "
                            + ("no loss (masked_pixels=ignore)" if cfg.masked_pixels == "ignore"
                               else f"trained toward the background {tuple(cfg.background)}"))
    own_xyz, own_rgb, reasons["sparse_points"] = sparse_points_for(scene, cfg, train)
    pts, rgb, tri, why = init_points_for(scene, cfg, train, (own_xyz, own_rgb))
    if cfg.init_triangulate_below is not None:
        reasons["init_points"] = why
    bounds = SceneBounds.from_inputs(cams.centers, pts, cfg.bounds_quantile)
    return TrainingData(sid, scene.root, cams, images, pts, rgb,
                        scene_extent(scene.cameras, own_xyz), scale, train, reasons,
                        bounds, dict(getattr(scene, "extras", {}) or {}), masks,
                        masks is not None and cfg.masked_pixels == "ignore",
                        len(own_xyz), tri)


def sparse_points_for(scene: Scene, cfg: ReconConfig, train: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, str]:
    """The scene's sparse points a training run may start from: with ``cfg.init_points``
    ``"train"`` only those the training views ``train`` alone could have triangulated (at
    least 2 views of their track are training views, :meth:`Scene.points_seen_by`); the others
    were placed, and coloured, with a held-out view. ``"all"``, or a scene without tracks:
    every point.

    Returns:
        ``(xyz [P', 3], rgb [P', 3] uint8, reason)``.
    """
    pts, rgb = scene.points_xyz, scene.points_rgb
    if cfg.init_points == "all":
        return pts, rgb, f"all {len(pts)} sparse points (init_points=all)"
    keep = scene.points_seen_by(train, 2)
    if keep is None:
        return pts, rgb, f"all {len(pts)} sparse points (the source gives no tracks)"
    if keep.all():
        return pts, rgb, f"all {len(pts)} sparse points (each seen by >= 2 training views)"
    return pts[keep], rgb[keep], (
        f"{int(keep.sum())} of {len(pts)} sparse points: the other {int((~keep).sum())} were "
        f"triangulated with a view outside the {len(train)} training views")


def init_points_for(scene: Scene, cfg: ReconConfig, train: np.ndarray,
                    own: tuple[np.ndarray, np.ndarray] | None = None
                    ) -> tuple[np.ndarray, np.ndarray, dict | None, str]:
    """The points the Gaussians start from: the scene's sparse points (``own``, default all
    of them; :func:`sparse_points_for`), plus points triangulated from the training views
    ``train`` (never a held-out view) when there are fewer than ``cfg.init_triangulate_below``
    sparse points per training view.

    Returns:
        ``(xyz [P, 3], rgb [P, 3] uint8, triangulation stats or None, reason)``.
    """
    pts, rgb = (scene.points_xyz, scene.points_rgb) if own is None else own
    per_view = len(pts) / max(len(train), 1)
    thr = cfg.init_triangulate_below
    if thr is None:
        return pts, rgb, None, f"{len(pts)} sparse points (triangulation off)"
    if per_view >= thr or len(train) < 2:
        return pts, rgb, None, (f"{len(pts)} sparse points = {per_view:.0f} per training view "
                                f"(>= {thr:g} or < 2 views): not triangulated")
    from freescale_core.scene.triangulate import merge_points, triangulate_views

    t = triangulate_views(scene, train, min_views=cfg.init_triangulate_min_views)
    st = t.stats
    if len(pts) == 0 and len(t) < 4:  # too few to start from: random points as without
        return pts, rgb, None, f"no sparse points and only {len(t)} triangulated: not used"
    info = {"n_added": len(t), "n_given": len(pts), "seconds": st["seconds"],
            "cpu_seconds": st.get("cpu_seconds"), "median_reproj_px": st.get("median_reproj_px"),
            "n_views": len(train), "n_matches": st.get("n_matches"), "scale": st.get("scale")}
    pts, rgb = merge_points(pts, rgb, t)
    return pts, rgb, info, (f"{info['n_given']} sparse points = {per_view:.0f} per training view "
                            f"< {thr:g}: +{len(t)} triangulated from {len(train)} training views "
                            f"in {st['seconds']:.1f} s")
