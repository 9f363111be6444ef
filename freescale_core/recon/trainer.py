"""Reconstruction: 3D Gaussians from a scene's images and cameras (METHOD.md stage 1).

``reconstruct`` is a pure function (Scene in, Gaussians out): the caller writes the PLY.
It follows the paper's recipe (sparse-point init at opacity 0.5, loss (1 - 0.2) L1 +
0.2 (1 - SSIM), Adam with the 3DGS learning rates, MCMC densification, SH degree schedule)
and sizes the model to the scene instead of using fixed maxima:

* training resolution: :func:`choose_resolution` (long-side cap + "does the image hold detail
  at this scale" round-trip test);
* Gaussian budget: :func:`choose_budget` (from sparse point count and training pixels);
* iteration count: :func:`plateau_reached` on an EMA of the loss. The first plateau while
  still growing stops growth (the scene needs no more Gaussians); the next plateau starts a
  short final annealing of the means learning rate, after which training stops.

Every choice and its reason go into ``ReconResult.stats["reasons"]``. See docs/RECON.md.

Shape: :func:`train` is the loop; it draws views from a ``ViewSource``
(:mod:`freescale_core.recon.views`: image, camera, loss weight, mask) and leaves the Gaussian
set to a ``Strategy`` (:mod:`freescale_core.recon.strategy`: MCMC or none, with
``step_pre_backward`` / ``on_plateau`` / ``step_post_backward`` hooks, including the bound
that keeps Gaussians in the scene, :mod:`freescale_core.recon.bounds`). :func:`reconstruct`
is ``train`` on a scene's views. Thread counts are set by :mod:`freescale_core.threads`.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import torch

from schemas.recon import ReconConfig

from freescale_core.recon.bounds import SceneBounds, extent_report
from freescale_core.recon.strategy import Strategy, make_strategy
from freescale_core.threads import compute_threads
from freescale_core.geometry.cameras import Cameras
from freescale_core.errors import DegenerateSceneError
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.images import resize_area as _resize  # old name, still imported
from freescale_core.recon.losses import masked_photometric_loss, masked_psnr_ssim
from freescale_core.scene.scene import Scene



@dataclass
class ReconResult:
    """Output of :func:`reconstruct`.

    Attributes:
        gaussians: the trained Gaussians (unactivated parameters, unit quaternions, SH trimmed
            to the degree reached).
        stats: ``n_gaussians``, ``iterations``, ``train_resolution`` (w, h),
            ``recon_seconds``, ``recon_train_psnr``, ``reasons`` (why each size was chosen),
            ``loss`` (history summary) and more; JSON-serialisable.
    """

    gaussians: Gaussians
    stats: dict = field(default_factory=dict)


def _rasterize(*args, **kwargs):
    """Indirection so tests can substitute the rasterizer (monkeypatch this name)."""
    from freescale_core.raster import rasterize

    return rasterize(*args, **kwargs)


# =========================================================================== sizing rules
def image_peak(image: np.ndarray, q: float = 99.5) -> float:
    """The image's own white level: the ``q``-th percentile of its values (uint8 scale, at
    least 1). A well-exposed photo is close to 255; a dark capture far below it."""
    return float(max(1.0, np.percentile(image, q)))


def roundtrip_psnr(image: np.ndarray, factor: int, peak: float = 255.0) -> float:
    """PSNR (dB) of ``image [H, W, 3]`` uint8 against itself downscaled by ``factor`` (area)
    and upscaled back (bicubic), with ``peak`` as the signal's full scale: high means the
    image holds no detail at the finer scale."""
    import cv2

    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, w // factor), max(1, h // factor)),
                       interpolation=cv2.INTER_AREA)
    back = cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
    mse = np.mean((image.astype(np.float64) - back.astype(np.float64)) ** 2) / float(peak) ** 2
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


def choose_resolution(widths: Sequence[int], heights: Sequence[int], cfg: ReconConfig,
                      sample_images: Sequence[np.ndarray] = ()) -> tuple[float, str]:
    """Resolution rule: one scale factor for all training images of a scene.

    1. cap: ``s = min(1, max_long_side / longest side)``;
    2. detail: if ``cfg.detail_psnr_db`` is set, divide ``s`` by the largest factor ``f`` in
       ``cfg.detail_factors`` for which every sample image (already at scale ``s``) survives a
       down-by-``f``/up round trip above ``detail_psnr_db`` (blurry or upsampled captures).
       The PSNR is taken against each image's own white level (:func:`image_peak`), not 255:
       a dark capture's detail is small in grey levels but not absent (on kermit scaled to
       15% brightness the 255-scale test read 42 dB at x2 and downscaled; against its white
       level it reads 25 dB, like the original's 26).

    Args:
        widths, heights: ``[N]`` native image sizes.
        sample_images: a few ``[H, W, 3]`` uint8 training images at native size.
    Returns:
        ``(scale, reason)``.
    """
    import cv2

    long_side = int(max(max(widths), max(heights)))
    s = min(1.0, cfg.max_long_side / long_side)
    reason = (f"long side {long_side} px <= cap {cfg.max_long_side}: native size" if s == 1.0
              else f"long side {long_side} px > cap {cfg.max_long_side}: scale {s:.4f}")
    if cfg.detail_psnr_db is None or not len(sample_images):
        return s, reason
    scaled = []
    for img in sample_images:
        h, w = img.shape[:2]
        scaled.append(img if s == 1.0 else cv2.resize(
            img, (max(1, round(w * s)), max(1, round(h * s))), interpolation=cv2.INTER_AREA))
    best, best_db, stop = 1, None, ""
    for f in sorted(cfg.detail_factors):
        if min(min(im.shape[:2]) for im in scaled) // f < 16:
            break
        db = min(roundtrip_psnr(im, f, image_peak(im)) for im in scaled)
        if db < cfg.detail_psnr_db:
            stop = (f"down-up x{f} round trip {db:.1f} dB < {cfg.detail_psnr_db:g} dB: "
                    f"detail at this scale")
            break
        best, best_db = f, db
    if best > 1:
        reason += (f"; down-up x{best} round trip {best_db:.1f} dB >= {cfg.detail_psnr_db:g} dB: "
                   f"no detail lost, downscale by {best}")
    if stop:
        reason += f"; {stop}"
    return s / best, reason


def choose_budget(n_points: int, n_views: int, pixels_per_view: float, cfg: ReconConfig
                  ) -> tuple[int, str]:
    """Budget rule: ``clamp(max(k_p * points, pixels / p_g), budget_min, cap_gaussians)``.

    ``k_p = cfg.budget_per_point`` (Gaussians per sparse point: geometric detail found by SfM),
    ``p_g = cfg.budget_pixels_per_gaussian`` (training pixels per Gaussian: texture detail).

    Args:
        n_points: sparse SfM points. n_views: training views.
        pixels_per_view: mean pixels of one training image at the training resolution.
    Returns:
        ``(budget, reason)``.
    """
    from_points = cfg.budget_per_point * n_points
    total_px = n_views * pixels_per_view
    from_pixels = total_px / cfg.budget_pixels_per_gaussian
    raw = max(from_points, from_pixels)
    budget = int(min(max(raw, cfg.budget_min), cfg.cap_gaussians))
    driver = "points" if from_points >= from_pixels else "pixels"
    reason = (f"max({cfg.budget_per_point:g} x {n_points} points = {int(from_points)}, "
              f"{total_px:.0f} px / {cfg.budget_pixels_per_gaussian:g} = {int(from_pixels)}) "
              f"-> {int(raw)} ({driver})")
    if budget != int(raw):
        reason += (f", clamped to [{cfg.budget_min}, {cfg.cap_gaussians}] -> {budget}")
    return budget, reason


def choose_sh_degree(n_views: int, cfg: ReconConfig,
                     gain_spread: float | None = None) -> tuple[int, str]:
    """Highest SH degree the training views can constrain: ``cfg.sh_degree`` capped at the
    largest ``d`` with ``cfg.sh_views_per_coeff * (d + 1) ** 2 <= n_views``, never below 1.

    Degree ``d`` gives each Gaussian ``(d + 1) ** 2`` colour coefficients per channel; a
    Gaussian that fewer views see than a small multiple of that can fit the training views
    with colour that no other direction shares. ``sh_views_per_coeff=None`` keeps
    ``cfg.sh_degree``.

    With ``cfg.sh_cap_min_gain_std = t`` the cap applies only when the training views'
    exposure disagrees: ``gain_spread`` (the std of their log colour gains,
    :func:`freescale_core.recon.photometric.gain_spread`) above ``t``, or None (not
    measurable: the cap applies, as without the rule). On the five shared scenes this caps
    exactly the one the cap helped (buddha); the supposed reason, that high-degree SH fits
    each photo's exposure, was not supported by a test on painted sample scenes, so the rule
    is an empirical one (docs/RECON.md, "The SH cap only where the views disagree").

    Returns:
        ``(degree, reason)``.
    """
    if cfg.sh_views_per_coeff is None:
        return cfg.sh_degree, f"max {cfg.sh_degree} (no view-count cap)"
    t = cfg.sh_cap_min_gain_std
    if t is not None and gain_spread is not None and gain_spread <= t:
        return cfg.sh_degree, (f"max {cfg.sh_degree}: view-count cap off, the training views' "
                               f"log colour gain std {gain_spread:.3f} <= {t:g}")
    d = 0
    while d < 3 and cfg.sh_views_per_coeff * (d + 2) ** 2 <= n_views:
        d += 1
    deg = min(cfg.sh_degree, max(1, d))
    k = cfg.sh_views_per_coeff
    holds = f"up to d = {d}" if k <= n_views else "for no d"
    why = ("" if t is None else
           f"; log colour gain std {gain_spread:.3f} > {t:g}" if gain_spread is not None else
           "; log colour gain spread not measurable")
    return deg, (f"max {deg}: {n_views} training views, {k:g} x (d+1)^2 <= {n_views} holds "
                 f"{holds} (at least 1, at most {cfg.sh_degree}){why}")


def ema_series(losses: Sequence[float], halflife: float) -> np.ndarray:
    """Exponential moving average ``[T]`` of ``losses [T]`` with the given half-life (steps),
    bias-corrected so early values are not pulled towards 0."""
    beta = 0.5 ** (1.0 / halflife)
    out = np.empty(len(losses))
    m, w = 0.0, 0.0
    for i, x in enumerate(losses):
        m = beta * m + (1 - beta) * float(x)
        w = beta * w + (1 - beta)
        out[i] = m / w
    return out


def plateau_reached(ema: Sequence[float], window: int, tol: float) -> bool:
    """Plateau rule: the loss EMA improved by less than ``tol`` (relative) over ``window`` steps.

    Args:
        ema: ``[T]`` loss EMA up to now (one value per step).
    Returns:
        False while fewer than ``window + 1`` values exist.
    """
    if len(ema) <= window:
        return False
    prev, now = float(ema[-1 - window]), float(ema[-1])
    return (prev - now) < tol * max(abs(prev), 1e-12)


def scene_extent(cameras: Cameras, points_xyz: np.ndarray | None = None) -> float:
    """3DGS ``spatial_lr_scale``: 1.1 x the largest camera distance from the camera centroid
    (falls back to the sparse points' spread when all cameras coincide)."""
    c = cameras.centers
    r = float(np.max(np.linalg.norm(c - c.mean(0), axis=1))) if len(c) else 0.0
    if r < 1e-9 and points_xyz is not None and len(points_xyz):
        r = float(np.max(np.linalg.norm(points_xyz - points_xyz.mean(0), axis=1)))
    return 1.1 * max(r, 1e-6)


def means_lr(progress: float, cfg: ReconConfig, extent: float) -> float:
    """3DGS exponential decay from ``lr_means_init`` (progress 0) to ``lr_means_final`` (1),
    times the scene extent."""
    return extent * exp_decay(cfg.lr_means_init, cfg.lr_means_final, progress)


def exp_decay(start: float, end: float, progress: float) -> float:
    """3DGS's learning-rate decay: log-linear from ``start`` (progress 0) to ``end`` (1)."""
    p = min(max(progress, 0.0), 1.0)
    return math.exp((1 - p) * math.log(start) + p * math.log(end))


# =========================================================================== optimiser
class _Adam:
    """Adam over a dict of tensors whose row count changes (densification)."""

    def __init__(self, params: dict[str, torch.Tensor], betas=(0.9, 0.999), eps=1e-15):
        self.b1, self.b2, self.eps = betas[0], betas[1], eps
        self.m = {k: torch.zeros_like(p.data) for k, p in params.items()}
        self.v = {k: torch.zeros_like(p.data) for k, p in params.items()}
        self.t = 0

    @torch.no_grad()
    def step(self, params: dict[str, torch.Tensor], lrs: dict[str, float]) -> None:
        self.t += 1
        bc1, bc2 = 1 - self.b1**self.t, 1 - self.b2**self.t
        for k, p in params.items():
            g = p.grad
            if g is None:
                continue
            m, v = self.m[k], self.v[k]
            m.mul_(self.b1).add_(g, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
            p.data.addcdiv_(m, (v / bc2).sqrt_().add_(self.eps), value=-lrs[k] / bc1)

    def reset_rows(self, rows: np.ndarray) -> None:
        if len(rows):
            idx = torch.from_numpy(np.asarray(rows, np.int64))
            for k in self.m:
                self.m[k][idx] = 0
                self.v[k][idx] = 0

    def append_rows(self, n: int) -> None:
        for d in (self.m, self.v):
            for k in d:
                d[k] = torch.cat([d[k], d[k].new_zeros((n,) + tuple(d[k].shape[1:]))])


class _Background:
    """A learned RGB background colour: a captured view's render is composited on it as
    ``rgb_on_black + (1 - alpha) * colour`` (the rasterizer's alpha carries the Gaussians'
    share of the gradient), the colour learned by its own Adam and kept in [0, 1]. Starts at
    ``cfg.background``. Held-out renders use the learned colour (``stats["background"]``)."""

    def __init__(self, start, lr: float, lr_final: float | None = None):
        self.c = torch.tensor([float(v) for v in start], dtype=torch.float32, requires_grad=True)
        self.opt = torch.optim.Adam([self.c], lr=lr, eps=1e-15)
        self.lr0, self.lr1 = float(lr), (None if lr_final is None else float(lr_final))

    def set_progress(self, p: float) -> None:
        """``background_lr_final``: the rate at training progress ``p`` in [0, 1], decayed
        exponentially as the means' is. Adam takes full-rate steps whatever the gradient's
        size, so a colour few pixels pin keeps moving at the full rate while the Gaussians'
        rates anneal; the decay lets it settle with them."""
        if self.lr1 is None:
            return
        lr = exp_decay(self.lr0, self.lr1, p)
        for g in self.opt.param_groups:
            g["lr"] = lr

    def lr(self) -> float:
        return float(self.opt.param_groups[0]["lr"])

    def composite(self, rgb: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        return rgb + (1.0 - alpha)[..., None] * self.c

    def step(self) -> None:
        if self.c.grad is not None:
            self.opt.step()
            with torch.no_grad():
                self.c.clamp_(0.0, 1.0)
        self.opt.zero_grad(set_to_none=True)

    def colour(self) -> tuple[float, float, float]:
        return tuple(float(v) for v in self.c.detach())


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


@dataclass
class TrainState:
    """The loop's mutable state, handed to strategies and callbacks."""

    params: dict
    opt: "_Adam"
    rng: np.random.Generator
    gen: torch.Generator
    data: TrainingData
    step: int = 0


def reconstruct(scene: Scene, cfg: ReconConfig | None = None, seed: int = 0,
                train_idx: Sequence[int] | np.ndarray | None = None,
                progress: Callable[[int, dict], None] | None = None,
                checkpoint_every: int = 0,
                on_checkpoint: Callable[[int, Gaussians, dict], bool | None] | None = None
                ) -> ReconResult:
    """Fit 3D Gaussians to a scene's training views (METHOD.md stage 1).

    Same as :func:`train` on the scene's views ``train_idx`` (kept as the stage's entry point).

    Args:
        scene: cameras, images and sparse points (``Scene``).
        cfg: :class:`ReconConfig` (default: paper settings).
        seed: seeds torch and numpy; same seed and inputs give identical parameters.
        train_idx: camera indices to train on (default: all views).
        progress: optional ``progress(step, info)`` called every 10 steps and at the end;
            ``info`` has ``loss_ema``, ``n_gaussians``, ``phase``, ``sh_degree``.
        checkpoint_every: call ``on_checkpoint`` every this many steps (0: never).
        on_checkpoint: ``on_checkpoint(step, gaussians, info)`` with a copy of the current
            Gaussians (SH trimmed to the current degree) and ``info`` = ``train_seconds``
            (training clock so far), ``train_scale``, ``sh_degree``. The clock is paused
            while it runs: its time counts neither towards ``max_seconds`` nor
            ``recon_seconds`` (it is reported as ``stats["checkpoint_seconds"]``), and it
            does not touch the training's random state. Returning ``True`` ends training
            at that step (no annealing; the schedule up to there is unchanged), e.g. to read
            the first minutes of a long budget's curve without changing its schedule.
    Returns:
        :class:`ReconResult`.
    Raises:
        DegenerateSceneError: too few points/views, or training produced non-finite values.
    """
    return train(scene, cfg, seed, train_idx=train_idx, progress=progress,
                 checkpoint_every=checkpoint_every, on_checkpoint=on_checkpoint)


def train(scene_or_data: Scene | TrainingData, cfg: ReconConfig | None = None, seed: int = 0,
          view_source=None, strategy: Strategy | None = None, *,
          train_idx: Sequence[int] | np.ndarray | None = None,
          progress: Callable[[int, dict], None] | None = None,
          checkpoint_every: int = 0,
          on_checkpoint: Callable[[int, Gaussians, dict], bool | None] | None = None,
          on_step: Sequence[Callable[[int, "TrainState", dict], None]] = (),
          profile: dict[str, list[float]] | None = None) -> ReconResult:
    """The training loop: Gaussians from views (METHOD.md stage 1).

    Args:
        scene_or_data: a ``Scene`` (its views ``train_idx`` are loaded at the resolution the
            resolution rule picks, see :func:`prepare`) or a prepared :class:`TrainingData`.
        cfg: :class:`ReconConfig`.
        seed: seeds numpy and torch; same seed and inputs give identical parameters.
        view_source: a :class:`freescale_core.recon.views.ViewSource` (default: the captured
            views, :class:`~freescale_core.recon.views.CapturedViews`); each view carries its
            loss weight and optional mask.
        strategy: a :class:`freescale_core.recon.strategy.Strategy` (default: ``cfg.densify``).
        progress, checkpoint_every, on_checkpoint: as in :func:`reconstruct`.
        on_step: callables ``f(step, state, info)`` after every step (``info``: ``loss``,
            ``view`` (the :class:`View`), ``lr_means``, ``phase``).
        profile: when a dict, filled with ``{section: [wall s, process-CPU s]}`` summed over
            all steps, for the sections of one step (``view``, ``raster_forward``, ``loss``,
            ``backward``, ``optimizer``, ``strategy`` (densification, noise, bounds),
            ``other``); ``benchmarks/recon.py --breakdown`` prints it per step.
    """
    cfg = cfg or ReconConfig()
    t0 = _clock(cfg)()
    with compute_threads(cfg.torch_threads, cfg.threads or os.cpu_count() or 1):
        data = (scene_or_data if isinstance(scene_or_data, TrainingData)
                else prepare(scene_or_data, cfg, train_idx))
        return _train(data, cfg, seed, view_source, strategy, progress, t0,
                      (checkpoint_every, on_checkpoint), tuple(on_step), profile)


class _Laps:
    """Per-section wall and process-CPU seconds of the training step (``profile``); a no-op
    unless a dict is given, so the loop pays two attribute lookups per section."""

    def __init__(self, out: dict[str, list[float]] | None):
        self.out = out
        self.t = (time.perf_counter(), time.process_time()) if out is not None else None

    def lap(self, name: str) -> None:
        if self.out is None:
            return
        now = (time.perf_counter(), time.process_time())
        acc = self.out.setdefault(name, [0.0, 0.0])
        acc[0] += now[0] - self.t[0]
        acc[1] += now[1] - self.t[1]
        self.t = now


def _train(data: TrainingData, cfg, seed, view_source, strategy, progress, t0,
           checkpoint=(0, None), on_step=(), profile=None) -> ReconResult:
    import numba

    from freescale_core.recon.views import CapturedViews

    sid = data.scene_id
    clock = _clock(cfg)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    gen = torch.Generator().manual_seed(seed)
    reasons: dict[str, str] = dict(data.reasons)
    cams, images = data.cams, data.images
    n_train = len(images)
    res = (int(cams.width.max()), int(cams.height.max()))
    px_per_view = float(np.mean(cams.width * cams.height))

    # ---- budget and init
    # the budget counts the scene's own points: triangulated ones change the start, not the size
    budget, reasons["n_gaussians_budget"] = choose_budget(data.n_own_points, n_train,
                                                          px_per_view, cfg)
    params, reasons["init"] = _init_params(data, cfg, budget, rng)
    gain_std, gain_on = _gain_spread(data) if _wants_gain_spread(cfg) else (None, "")
    sh_max, sh_why = choose_sh_degree(n_train, cfg, gain_std)
    n_init = params["means"].shape[0]
    extent = data.extent
    # a batch of B views per step: the square-root learning-rate rule and Adam's averaging
    # horizon kept in views (beta -> 1 - B (1 - beta); the schema's B <= 8 keeps beta1 >= 0.2),
    # as large-batch 3DGS training does
    nb = cfg.batch_views
    lr_mult = math.sqrt(nb)
    betas = (0.9, 0.999) if nb == 1 else (1 - nb * (1 - 0.9), 1 - nb * (1 - 0.999))
    state = TrainState(params, _Adam(params, betas=betas), rng, gen, data)
    strategy = strategy if strategy is not None else make_strategy(cfg)
    strategy.initialize(state, budget)
    views = (view_source if view_source is not None
             else CapturedViews(data, _c2f_levels(cfg, data)))

    # ---- loop state
    halflife = max(cfg.plateau_ema_halflife, 2.0 * n_train)
    beta = 0.5 ** (1.0 / halflife)
    # The EMA is one view's loss at step 1 and needs about a half-life to average the views;
    # a window shorter than the half-life cannot see an improvement through the EMA's lag.
    # Without these two guards a 34-view scene (half-life 68) "plateaued" at step 62 of the
    # fast preset (window 60) at 10 dB (dtu_scan24, OOD split).
    warmup = int(math.ceil(halflife))
    window = max(cfg.plateau_window, warmup)
    # A coarse-to-fine level's loss (smoother, smaller images) is lower than the full
    # resolution's, so a window reaching back across the last switch compares unlike losses
    # and reads a plateau that is not there: llff_fern's cpu preset (switch at step 600)
    # "plateaued" at step 1000 and stopped growing at 23.6k of its 64.7k Gaussians. The
    # window starts after the last switch and the EMA's warm-up past it.
    plateau_from = warmup + max((s for s, _ in _c2f_levels(cfg, data)), default=0)
    ema_m = ema_w = 0.0
    ema_hist: list[float] = []
    last_event = 0
    anneal_start: int | None = None
    anneal_len = 0
    anneal_p0 = 0.0
    stop_reason = f"max_iterations {cfg.max_iterations} reached"
    history: list[tuple[int, float, int]] = []
    bg = tuple(float(v) for v in cfg.background)
    learned_bg = None
    if cfg.background_lr is not None:
        if data.masks is None:
            learned_bg = _Background(bg, cfg.background_lr, cfg.background_lr_final)
            reasons["background"] = (f"learned behind unmasked photos from {bg} "
                                     f"(background_lr {cfg.background_lr:g}"
                                     + ("" if cfg.background_lr_final is None else
                                        f", decaying to {cfg.background_lr_final:g} with the means'")
                                     + ")")
        else:
            reasons["background"] = f"background_lr off: object masks, so {bg} behind every photo"
    # the gate (background_min_uncovered): the share of training pixels the Gaussians leave to
    # the colour (alpha < 0.5) over steps (K/2, K]; below the threshold the scene does not need
    # a learned colour, which then only moves with the few pixels that pin it
    gate_k = cfg.background_gate_step if (learned_bg is not None and
                                          cfg.background_min_uncovered is not None) else None
    gate_sum = gate_n = 0.0
    uncovered_share = None
    step = 0
    loss_first = None
    ck_every, ck_fn = checkpoint
    ck_seconds = 0.0
    laps = _Laps(profile)
    for step in range(1, cfg.max_iterations + 1):
        state.step = step
        params = state.params
        # --- learning rates and SH degree
        if anneal_start is None:
            p = step / cfg.max_iterations
        else:
            p = anneal_p0 + (1 - anneal_p0) * (step - anneal_start) / max(anneal_len, 1)
        lr_mu = means_lr(p, cfg, extent)
        if learned_bg is not None:
            learned_bg.set_progress(p)
        lrs = {"means": lr_mu, "log_scales": cfg.lr_scales, "quats_wxyz": cfg.lr_quats,
               "opacity_logits": cfg.lr_opacity, "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest}
        if nb > 1:
            lrs = {k: v * lr_mult for k, v in lrs.items()}
            lr_mu = lrs["means"]
        deg = min(sh_max, (step - 1) // cfg.sh_increase_every)

        # --- one training view (or a batch of cfg.batch_views) from the view source
        laps.lap("other")  # learning rates, SH degree, the previous step's callbacks
        for prm in params.values():
            prm.grad = None
        photo = 0.0
        sh = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
        for b in range(nb):
            view = views.next(step, rng)
            laps.lap("view")
            cam = view.camera
            bg_view = bg
            learn_here = learned_bg is not None and view.kind == "captured"
            if learn_here:
                bg_view = (0.0, 0.0, 0.0)  # composited on the learned colour below
            out = _rasterize(params["means"], params["log_scales"], params["quats_wxyz"],
                             params["opacity_logits"], sh, cam.world_from_cam, cam.fx, cam.fy,
                             cam.cx, cam.cy, cam.width, cam.height,
                             sh_degree=deg, background=bg_view, backend=cfg.raster_backend,
                             exact_tiles=cfg.raster_exact_tiles)
            laps.lap("raster_forward")
            lam = cfg.lambda_ssim if view.lambda_ssim is None else view.lambda_ssim
            rgb = out.rgb
            if learn_here:
                rgb = learned_bg.composite(rgb, out.alpha)
                if gate_k is not None and step > gate_k // 2:
                    gate_sum += float((out.alpha.detach() < 0.5).float().mean())
                    gate_n += 1
            loss = masked_photometric_loss(rgb, view.target(), view.mask, lam, cfg.ssim_impl)
            if view.weight != 1.0:
                loss = view.weight * loss
            photo_b = float(loss.detach())
            if not math.isfinite(photo_b):
                raise DegenerateSceneError(
                    sid, f"training diverged: non-finite loss at step {step} "
                    f"(view {_view_name(data, view)})", data.root)
            photo += photo_b / nb
            if nb > 1:
                loss = loss / nb
            if b == 0:
                extra = strategy.step_pre_backward(state, step, {"lr_means": lr_mu})
                if extra is not None:
                    loss = loss + extra
            laps.lap("loss")
            # the graph of sh is shared by the batch's renders: kept until the last backward
            loss.backward(retain_graph=b < nb - 1)
            laps.lap("backward")
        state.opt.step(params, lrs)
        if learned_bg is not None:
            learned_bg.step()
            if gate_k is not None and step == gate_k:
                uncovered_share = gate_sum / max(gate_n, 1.0)
                keep = uncovered_share >= cfg.background_min_uncovered
                reasons["background"] += (
                    f"; {100 * uncovered_share:.2f}% of training pixels below alpha 0.5 over "
                    f"steps {gate_k // 2 + 1}-{gate_k} "
                    + ("kept it" if keep else f"< {100 * cfg.background_min_uncovered:g}%: "
                       f"back to {bg}, fixed, from step {gate_k}"))
                gate_k = None
                if not keep:
                    learned_bg = None
        laps.lap("optimizer")

        # --- loss EMA and plateau rule
        loss_first = photo if loss_first is None else loss_first
        ema_m = beta * ema_m + (1 - beta) * photo
        ema_w = beta * ema_w + (1 - beta)
        ema_hist.append(ema_m / ema_w)
        n_now = params["means"].shape[0]
        if step % max(1, cfg.max_iterations // 200) == 0 or step == 1:
            history.append((step, ema_hist[-1], n_now))
        stopping = False
        if anneal_start is None:
            event = None
            if (step >= cfg.min_iterations and step - last_event >= window
                    and step - window >= plateau_from
                    and plateau_reached(ema_hist, window, cfg.plateau_tol)):
                event = "plateau"
            elif cfg.max_seconds is not None and clock() - t0 >= _anneal_threshold(cfg):
                event = "time"  # leave room for the annealing inside the budget
            if event == "plateau" and strategy.on_plateau(state, step) is not None:
                last_event = step
                reasons["growth_stop"] = (
                    f"loss EMA improved < {cfg.plateau_tol:.0%} over {window} steps "
                    f"at step {step} with {n_now} Gaussians (budget {budget}): growth stopped")
            elif event is not None:
                anneal_start, anneal_p0 = step, p
                anneal_len = max(1, int(round(cfg.anneal_fraction * step)))
                anneal_len = min(anneal_len, cfg.max_iterations - step)
                why = (f"loss EMA improved < {cfg.plateau_tol:.0%} over {window} "
                       f"steps at step {step}" if event == "plateau"
                       else f"{_anneal_threshold(cfg):.0f} s of the time "
                       f"budget {cfg.max_seconds:g} s used at step {step}")
                stop_reason = f"{why}; then {anneal_len} annealing steps"
                stopping = anneal_len == 0
        elif step - anneal_start >= anneal_len:
            stopping = True
        elif cfg.max_seconds is not None and clock() - t0 >= cfg.max_seconds:
            stop_reason += f" (cut at step {step}: time budget {cfg.max_seconds:g} s)"
            stopping = True

        laps.lap("other")
        # --- densification strategy (noise, relocation, growth; none while annealing)
        strategy.step_post_backward(state, step, {"lr_means": lr_mu, "stopping": stopping,
                                                  "annealing": anneal_start is not None,
                                                  "view": view})
        if step % cfg.nan_check_every == 0:
            _check_finite(state.params, data, step)
        laps.lap("strategy")
        if stopping:
            break
        phase = ("anneal" if anneal_start is not None else
                 ("grow" if strategy.growing else "refine"))
        for cb in on_step:
            cb(step, state, {"loss": photo, "view": view, "lr_means": lr_mu, "phase": phase})
        if progress is not None and step % 10 == 0:
            progress(step, {"loss_ema": ema_hist[-1], "n_gaussians": state.params["means"].shape[0],
                            "phase": phase, "sh_degree": deg})
        if ck_fn is not None and ck_every > 0 and step % ck_every == 0:
            t_ck = clock()
            g_now = _to_gaussians({k: p.detach().clone() for k, p in state.params.items()}, deg)
            halt = ck_fn(step, g_now, {"train_seconds": t_ck - t0, "train_scale": data.scale,
                                       "sh_degree": deg, "background": (
                                           bg if learned_bg is None else learned_bg.colour())})
            paused = clock() - t_ck
            ck_seconds += paused
            t0 += paused  # the training clock does not run during a checkpoint
            if halt is True:
                stop_reason = f"stopped by the caller's checkpoint at step {step}"
                break

    params = state.params
    _check_finite(params, data, step)
    n_dropped = 0
    if cfg.bounds_every and cfg.bounds_margin is not None and data.bounds is not None:
        # Gaussians that left the bound since the last check (near-transparent ones wander
        # with the MCMC noise between checks) are not part of the scene: drop them.
        keep = data.bounds.distance(params["means"]) <= cfg.bounds_margin
        n_dropped = int((~keep).sum())
        if n_dropped and keep.any():
            idx = torch.from_numpy(np.nonzero(keep)[0])
            params = {k: p.detach()[idx] for k, p in params.items()}
        else:
            n_dropped = 0
    reasons.setdefault("growth_stop", getattr(strategy, "growth_stop", None)
                       or strategy.stop_reason(state))
    reasons["iterations"] = stop_reason
    if gate_k is not None:  # the run ended before the gate's step: it did not decide
        reasons["background"] += f"; the run ended before step {gate_k}: the gate kept it"
    sh_deg = min(sh_max, (step - 1) // cfg.sh_increase_every)
    reasons["sh_degree"] = (f"degree {sh_deg} reached at step {step} "
                            f"(+1 every {cfg.sh_increase_every}, {sh_why})")
    gaussians = _to_gaussians(params, sh_deg)
    gaussians.validate(sid, str(data.root))
    train_seconds = clock() - t0
    if learned_bg is not None:
        bg = learned_bg.colour()

    # ---- train PSNR on evenly spaced training views at the training resolution
    pick = np.unique(np.linspace(0, n_train - 1, min(cfg.train_eval_views, n_train))
                     .astype(int))
    tmasks = getattr(data, "masks", None)
    ev = _evaluate_views(gaussians, cams.subset(pick), [images[k].numpy() for k in pick], bg,
                         cfg.raster_backend,
                         None if tmasks is None else [tmasks[k].numpy() for k in pick])
    ids = data.view_ids if data.view_ids is not None else np.arange(n_train)
    stats = {
        "scene": sid,
        "n_gaussians": len(gaussians),
        "n_gaussians_init": n_init,
        "n_gaussians_budget": budget,
        "iterations": step,
        "batch_views": nb,
        "train_resolution": list(res),
        "train_scale": data.scale,
        "n_train_views": n_train,
        "sh_degree": sh_deg,
        "recon_seconds": clock() - t0,
        "train_seconds": train_seconds,
        "checkpoint_seconds": ck_seconds,
        "clock": cfg.budget_clock,
        "iterations_per_second": step / train_seconds,
        "recon_train_psnr": ev["psnr_mean"],
        "recon_train_ssim": ev["ssim_mean"],
        "train_eval_views": [int(ids[k]) for k in pick],
        "scene_extent": extent,
        "dropped_out_of_bounds": n_dropped,
        "init_triangulation": data.triangulation,
        "gaussian_extent": (extent_report(gaussians.means, data.bounds) | {
            "bound_radius": data.bounds.radius}) if data.bounds is not None else None,
        "densify": {"strategy": strategy.name, **strategy.stats()},
        "exposure_gain_std": gain_std,
        "background": list(bg),
        "background_lr_end": learned_bg.lr() if learned_bg is not None else None,
        "background_uncovered_share": uncovered_share,
        "mcmc": strategy.stats() if strategy.name == "mcmc" else {},
        "reasons": reasons,
        "loss": {"first": loss_first, "final_ema": ema_hist[-1] if ema_hist else None,
                 "min_ema": float(min(ema_hist)) if ema_hist else None,
                 "history": [[s, float(e), int(n)] for s, e, n in history]},
        "seed": seed,
        "threads": {"numba": numba.get_num_threads(), "torch": torch.get_num_threads()},
    }
    if progress is not None:
        progress(step, {"loss_ema": stats["loss"]["final_ema"], "n_gaussians": len(gaussians),
                        "phase": "done", "sh_degree": sh_deg})
    return ReconResult(gaussians, stats)


def _wants_gain_spread(cfg) -> bool:
    """Whether a rule of ``cfg`` reads the training views' colour gain spread."""
    return cfg.sh_views_per_coeff is not None and cfg.sh_cap_min_gain_std is not None


def _gain_spread(data: TrainingData) -> tuple[float | None, str]:
    """The std over the training views of their log colour gains, measured on the scene's own
    sparse points (:mod:`freescale_core.recon.photometric`), None when too few views see
    enough usable points; and what it was measured on."""
    from freescale_core.recon.photometric import gain_spread, view_log_gains

    n = data.n_own_points
    g = view_log_gains(data.cams, data.images, data.points_xyz[:n], data.points_rgb[:n])
    return gain_spread(g), f"{int(np.isfinite(g).all(1).sum())} of {len(g)} views, {n} sparse points"


def _c2f_levels(cfg, data: TrainingData) -> list[tuple[int, int]]:
    """``cfg.coarse_to_fine`` without levels whose images would fall under the SSIM window."""
    short = int(min(data.cams.width.min(), data.cams.height.min()))
    return [(int(s), int(f)) for s, f in cfg.coarse_to_fine if short // int(f) >= 16]


def _anneal_threshold(cfg) -> float:
    """Budget seconds at which the annealing starts: the budget less ``anneal_fraction`` of the
    time before it."""
    return cfg.max_seconds / (1.0 + cfg.anneal_fraction)


def _clock(cfg) -> Callable[[], float]:
    """The training clock: wall (``perf_counter``) or this process's CPU time."""
    return time.process_time if cfg.budget_clock == "cpu" else time.perf_counter


def _view_name(data: TrainingData, view) -> str:
    if view.kind == "captured" and data.view_ids is not None and 0 <= view.index < len(
            data.view_ids):
        return str(int(data.view_ids[view.index]))
    return f"{view.kind} {view.index}"


# =========================================================================== evaluation
def _render_np(g: Gaussians, cams: Cameras, j: int, bg, backend: str) -> np.ndarray:
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    with torch.no_grad():
        out = _rasterize(t(g.means), t(g.log_scales), t(g.quats_wxyz), t(g.opacity_logits),
                         t(g.sh), cams.world_from_cam[j], float(cams.fx[j]), float(cams.fy[j]),
                         float(cams.cx[j]), float(cams.cy[j]), int(cams.width[j]),
                         int(cams.height[j]), background=bg, backend=backend)
    return np.clip(out.rgb.detach().cpu().numpy(), 0.0, 1.0)


def _evaluate_views(g: Gaussians, cams: Cameras, images: Sequence[np.ndarray], bg,
                    backend: str = "auto", masks: Sequence[np.ndarray] | None = None) -> dict:
    """PSNR / SSIM per view; with ``masks`` over each view's mask pixels only."""
    ps, ss = [], []
    for j, img in enumerate(images):
        rgb = torch.from_numpy(_render_np(g, cams, j, bg, backend)).double()
        ref = torch.from_numpy(np.asarray(img)).double() / 255.0
        m = None if masks is None else torch.from_numpy(np.asarray(masks[j], bool))
        p, s_ = masked_psnr_ssim(rgb, ref, m)
        ps.append(p)
        ss.append(s_)
    return {"psnr": ps, "ssim": ss, "psnr_mean": float(np.mean(ps)) if ps else float("nan"),
            "ssim_mean": float(np.mean(ss)) if ss else float("nan")}


def evaluate(gaussians: Gaussians, scene: Scene, idx: Sequence[int] | np.ndarray,
             long_side: int | None = None, scale: float | None = None,
             background=(0.0, 0.0, 0.0), backend: str = "auto",
             masks: Sequence[np.ndarray] | None = None) -> dict:
    """PSNR and SSIM of rendered views against the scene's images (held-out evaluation).

    Args:
        gaussians: the reconstruction.
        scene: the scene (ground-truth images and cameras).
        idx: camera indices to evaluate, e.g. ``scene.split("ood")[1]``.
        long_side: evaluate at images downscaled so the long side is at most this (the
            training resolution of :func:`reconstruct` is ``stats["train_scale"]``); or
        scale: an explicit scale factor (overrides ``long_side``). Default: native size.
        background: RGB behind the Gaussians (use the training background).
        backend: rasterizer backend (see :func:`freescale_core.raster.rasterize`).
        masks: per view of ``idx``, a boolean mask at the evaluated size: score only its
            pixels (e.g. the co-visible ones, :mod:`freescale_core.eval.covis`); combined
            with the scene's object masks where it has them.
    Returns:
        ``{"views": [...], "psnr": [...], "ssim": [...], "psnr_mean", "ssim_mean",
        "resolution": [[w, h], ...], "masked"}``; SSIM as
        :func:`freescale_core.recon.losses.ssim` (11x11 Gaussian window, equal to skimage's).
        A scene with object masks is scored on the mask pixels only (``masked`` True): the
        background of an object capture is not part of the reconstruction.
    """
    idx = np.asarray(idx, np.int64).reshape(-1)
    cams = scene.cameras.subset(idx) if len(idx) else None
    if cams is None:
        return {"views": [], "psnr": [], "ssim": [], "psnr_mean": float("nan"),
                "ssim_mean": float("nan"), "resolution": []}
    if scale is None:
        long = np.maximum(cams.width, cams.height)
        scale = 1.0 if long_side is None else float(min(1.0, long_side / long.max()))
    cams = cams.scaled(scale)
    images = [_resize(scene.load_image(int(i)), cams.width[j], cams.height[j])
              for j, i in enumerate(idx)]
    given = masks
    masks = None
    if getattr(scene, "has_masks", False):
        from freescale_core.scene.io.masks import resize_mask

        masks = [resize_mask(scene.load_mask(int(i)), int(cams.width[j]), int(cams.height[j]))
                 for j, i in enumerate(idx)]
    if given is not None:
        if len(given) != len(idx):
            raise ValueError(f"{scene.scene_id}: {len(given)} masks for {len(idx)} views")
        for j, m in enumerate(given):
            if np.shape(m) != (int(cams.height[j]), int(cams.width[j])):
                raise ValueError(f"{scene.scene_id}: mask {j} is {np.shape(m)}, the view is "
                                 f"{int(cams.height[j])}x{int(cams.width[j])}")
        masks = [np.asarray(m, bool) if masks is None else np.asarray(m, bool) & masks[j]
                 for j, m in enumerate(given)]
    ev = _evaluate_views(gaussians, cams, images, tuple(background), backend, masks)
    ev["masked"] = masks is not None
    ev["views"] = idx.tolist()
    ev["resolution"] = [[int(w), int(h)] for w, h in zip(cams.width, cams.height)]
    return ev
