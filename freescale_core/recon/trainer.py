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
The other plug-ins are called at fixed points of each step the same way: the background
colour (:class:`~freescale_core.recon.background.BackgroundPlugin`: fixed or learned, and its
gate), the SH degree (:class:`~freescale_core.recon.schedule.SHSchedule`) and the stopping
rule (:class:`~freescale_core.recon.schedule.Stopping`: progress, loss EMA, plateau / anneal /
time).

The pieces around the loop live beside it and are re-exported here under their old names:
sizing rules (:mod:`~freescale_core.recon.sizing`), input data and initial points
(:mod:`~freescale_core.recon.data`), Adam (:mod:`~freescale_core.recon.optim`), the learned
background colour (:mod:`~freescale_core.recon.background`) and evaluation
(:mod:`~freescale_core.recon.evaluation`).
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

from freescale_core.recon.bounds import extent_report
from freescale_core.recon.strategy import Strategy, make_strategy
from freescale_core.threads import compute_threads
from freescale_core.errors import DegenerateSceneError
from freescale_core.scene.gaussians import Gaussians
from freescale_core.scene.images import resize_area as _resize  # old name, still imported
from freescale_core.recon.losses import masked_photometric_loss
from freescale_core.scene.scene import Scene
from freescale_core.recon.background import BackgroundPlugin, _Background
from freescale_core.recon.data import (TrainingData, _check_finite, _init_params, _to_gaussians,
                                       init_points_for, prepare, sparse_points_for)
from freescale_core.recon.evaluation import _evaluate_views, _render_np, evaluate
from freescale_core.recon.optim import _Adam
from freescale_core.recon.schedule import (SHSchedule, Stopping, _gain_spread,
                                           _wants_gain_spread)
from freescale_core.recon.schedule import anneal_threshold as _anneal_threshold
from freescale_core.recon.sizing import (choose_budget, choose_resolution, choose_sh_degree,
                                         ema_series, exp_decay, image_peak, means_lr,
                                         plateau_reached, roundtrip_psnr, scene_extent)


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

    @property
    def background(self) -> tuple[float, float, float]:
        """The colour the Gaussians were trained on (learned when ``background_lr`` is set)."""
        return tuple(float(v) for v in self.stats["background"])  # type: ignore[return-value]

    def write_ply(self, path) -> None:
        """Save the Gaussians with their background colour (``scene.ply.read_background``)."""
        from freescale_core.scene.ply import write_ply

        write_ply(path, self.gaussians, background=self.background)


def training_loss(rgb: torch.Tensor, target: torch.Tensor, mask, lambda_ssim: float
                  ) -> torch.Tensor:
    """The training loss of one render: (1 - lambda) L1 + lambda (1 - SSIM) over the mask's
    pixels, SSIM by the fused kernels (:mod:`freescale_core.recon.fused_ssim`)."""
    return masked_photometric_loss(rgb, target, mask, lambda_ssim, "fused")


def _rasterize(*args, **kwargs):
    """Indirection so tests can substitute the rasterizer (monkeypatch this name)."""
    from freescale_core.raster import rasterize

    return rasterize(*args, **kwargs)


@dataclass
class TrainState:
    """The loop's mutable state, handed to strategies and callbacks."""

    params: dict
    opt: "_Adam"
    rng: np.random.Generator
    gen: torch.Generator
    data: TrainingData
    step: int = 0
    sh_degree: int = 0


def reconstruct(scene: Scene, cfg: ReconConfig | None = None, seed: int = 0,
                train_idx: Sequence[int] | np.ndarray | None = None,
                progress: Callable[[int, dict], None] | None = None,
                checkpoint_every: int = 0,
                on_checkpoint: Callable[[int, Gaussians, dict], bool | None] | None = None,
                *, strategy: Strategy | None = None, photometric: Callable | None = None,
                rasterizer: Callable | None = None, clock: str = "wall") -> ReconResult:
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
        strategy, photometric, rasterizer, clock: as in :func:`train`.
    Returns:
        :class:`ReconResult`.
    Raises:
        DegenerateSceneError: too few points/views, or training produced non-finite values.
    """
    return train(scene, cfg, seed, strategy=strategy, train_idx=train_idx, progress=progress,
                 checkpoint_every=checkpoint_every, on_checkpoint=on_checkpoint,
                 photometric=photometric, rasterizer=rasterizer, clock=clock)


def train(scene_or_data: Scene | TrainingData, cfg: ReconConfig | None = None, seed: int = 0,
          view_source=None, strategy: Strategy | None = None, *,
          train_idx: Sequence[int] | np.ndarray | None = None,
          progress: Callable[[int, dict], None] | None = None,
          checkpoint_every: int = 0,
          on_checkpoint: Callable[[int, Gaussians, dict], bool | None] | None = None,
          on_step: Sequence[Callable[[int, "TrainState", dict], None]] = (),
          profile: dict[str, list[float]] | None = None,
          photometric: Callable | None = None,
          rasterizer: Callable | None = None, clock: str = "wall") -> ReconResult:
    """The training loop: Gaussians from views (METHOD.md stage 1).

    Args:
        scene_or_data: a ``Scene`` (its views ``train_idx`` are loaded at the resolution the
            resolution rule picks, see :func:`prepare`) or a prepared :class:`TrainingData`.
        cfg: :class:`ReconConfig`.
        seed: seeds numpy and torch; same seed and inputs give identical parameters.
        view_source: a :class:`freescale_core.recon.views.ViewSource` (default: the captured
            views, :class:`~freescale_core.recon.views.CapturedViews`); each view carries its
            loss weight and optional mask (boolean, or a float per-pixel weight). A source
            with a ``bind(state)`` method is handed the loop's :class:`TrainState` before
            the first step (``state.params`` are the current Gaussians, ``state.sh_degree``
            the current SH degree), e.g. to render pseudo views from the model being trained.
        strategy: a :class:`freescale_core.recon.strategy.Strategy` (default: ``cfg.densify``).
        progress, checkpoint_every, on_checkpoint: as in :func:`reconstruct`.
        on_step: callables ``f(step, state, info)`` after every step (``info``: ``loss``,
            ``view`` (the :class:`View`), ``lr_means``, ``phase``).
        profile: when a dict, filled with ``{section: [wall s, process-CPU s]}`` summed over
            all steps, for the sections of one step (``view``, ``raster_forward``, ``loss``,
            ``backward``, ``optimizer``, ``strategy`` (densification, noise, bounds),
            ``other``); ``benchmarks/recon.py --breakdown`` prints it per step.
        photometric: the loss of one render, ``f(rgb, target, mask, lambda_ssim) -> scalar``
            (default :func:`training_loss`: L1 + SSIM with the fused SSIM kernels).
        rasterizer: called as :func:`freescale_core.raster.rasterize` for every training
            render (default: that function). The lab's legacy arms swap these two and the
            strategy for the code they used (``lab/legacy.py``).
        clock: ``"wall"`` or ``"cpu"`` (this process's CPU time): the clock of
            ``cfg.max_seconds`` and of the reported seconds (``stats["clock"]``); the
            benchmarks budget in CPU time so that a loaded machine does not shorten a run.
    """
    cfg = cfg or ReconConfig()
    if clock not in ("wall", "cpu"):
        raise ValueError(f"clock must be 'wall' or 'cpu', got {clock!r}")
    t0 = _clock(clock)()
    with compute_threads(cfg.torch_threads, cfg.threads or os.cpu_count() or 1):
        data = (scene_or_data if isinstance(scene_or_data, TrainingData)
                else prepare(scene_or_data, cfg, train_idx))
        return _train(data, cfg, seed, view_source, strategy, progress, t0,
                      (checkpoint_every, on_checkpoint), tuple(on_step), profile,
                      photometric or training_loss, rasterizer or _rasterize, clock)


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
           checkpoint=(0, None), on_step=(), profile=None, photometric=None,
           rasterizer=None, clock_name: str = "wall") -> ReconResult:
    import numba

    from freescale_core.recon.views import CapturedViews

    sid = data.scene_id
    clock = _clock(clock_name)
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
    sh = SHSchedule(cfg, data)
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
    if hasattr(views, "bind"):  # a source that renders from the model being trained
        views.bind(state)

    # ---- the plug-ins around the loop: stopping rule, background colour (the SH schedule above)
    stop = Stopping(cfg, n_train, _c2f_levels(cfg, data), lambda: clock() - t0)
    background = BackgroundPlugin(cfg, data, reasons)
    step = 0
    ck_every, ck_fn = checkpoint
    ck_seconds = 0.0
    laps = _Laps(profile)
    for step in range(1, cfg.max_iterations + 1):
        state.step = step
        params = state.params
        # --- learning rates and SH degree
        p = stop.progress(step)
        lr_mu = means_lr(p, cfg, extent)
        background.set_progress(p)
        lrs = {"means": lr_mu, "log_scales": cfg.lr_scales, "quats_wxyz": cfg.lr_quats,
               "opacity_logits": cfg.lr_opacity, "sh_dc": cfg.lr_sh_dc, "sh_rest": cfg.lr_sh_rest}
        if nb > 1:
            lrs = {k: v * lr_mult for k, v in lrs.items()}
            lr_mu = lrs["means"]
        deg = sh.degree(step)
        state.sh_degree = deg

        # --- one training view (or a batch of cfg.batch_views) from the view source
        laps.lap("other")  # learning rates, SH degree, the previous step's callbacks
        for prm in params.values():
            prm.grad = None
        photo = 0.0
        coeffs = torch.cat([params["sh_dc"], params["sh_rest"]], dim=1)
        for b in range(nb):
            view = views.next(step, rng)
            laps.lap("view")
            cam = view.camera
            bg_view, learn_here = background.for_view(view)  # learned: composited below
            out = rasterizer(params["means"], params["log_scales"], params["quats_wxyz"],
                             params["opacity_logits"], coeffs, cam.world_from_cam, cam.fx, cam.fy,
                             cam.cx, cam.cy, cam.width, cam.height,
                             sh_degree=deg, background=bg_view, backend=cfg.raster_backend)
            laps.lap("raster_forward")
            lam = cfg.lambda_ssim if view.lambda_ssim is None else view.lambda_ssim
            rgb = out.rgb
            if learn_here:
                rgb = background.composite(rgb, out.alpha, step)
            loss = photometric(rgb, view.target(), view.mask, lam)
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
            # the graph of coeffs is shared by the batch's renders: kept until the last backward
            loss.backward(retain_graph=b < nb - 1)
            laps.lap("backward")
        state.opt.step(params, lrs)
        background.after_optimizer(step, reasons)
        laps.lap("optimizer")

        # --- loss EMA and the plateau / anneal / time rule
        stopping = stop.after_step(step, photo, params["means"].shape[0], strategy, state,
                                   reasons, budget)

        laps.lap("other")
        # --- densification strategy (noise, relocation, growth; none while annealing)
        strategy.step_post_backward(state, step, {"lr_means": lr_mu, "stopping": stopping,
                                                  "annealing": stop.annealing,
                                                  "view": view})
        if step % cfg.nan_check_every == 0:
            _check_finite(state.params, data, step)
        laps.lap("strategy")
        if stopping:
            break
        phase = ("anneal" if stop.annealing else
                 ("grow" if strategy.growing else "refine"))
        for cb in on_step:
            cb(step, state, {"loss": photo, "view": view, "lr_means": lr_mu, "phase": phase})
        if progress is not None and step % 10 == 0:
            progress(step, {"loss_ema": stop.ema_hist[-1], "n_gaussians": state.params["means"].shape[0],
                            "phase": phase, "sh_degree": deg})
        if ck_fn is not None and ck_every > 0 and step % ck_every == 0:
            t_ck = clock()
            g_now = _to_gaussians({k: p.detach().clone() for k, p in state.params.items()}, deg)
            halt = ck_fn(step, g_now, {"train_seconds": t_ck - t0, "train_scale": data.scale,
                                       "sh_degree": deg, "background": background.colour()})
            paused = clock() - t_ck
            ck_seconds += paused
            t0 += paused  # the training clock does not run during a checkpoint
            if halt is True:
                stop.stop_reason = f"stopped by the caller's checkpoint at step {step}"
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
    reasons["iterations"] = stop.stop_reason
    bg = background.finish(reasons)
    sh_deg = sh.degree(step)
    reasons["sh_degree"] = sh.reason(step)
    gaussians = _to_gaussians(params, sh_deg)
    gaussians.validate(sid, str(data.root))
    train_seconds = clock() - t0

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
        "clock": clock_name,
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
        "exposure_gain_std": sh.gain_std,
        **background.stats(),
        "mcmc": strategy.stats() if strategy.name == "mcmc" else {},
        "reasons": reasons,
        "loss": stop.loss_stats(),
        "seed": seed,
        "threads": {"numba": numba.get_num_threads(), "torch": torch.get_num_threads()},
    }
    if progress is not None:
        progress(step, {"loss_ema": stats["loss"]["final_ema"], "n_gaussians": len(gaussians),
                        "phase": "done", "sh_degree": sh_deg})
    return ReconResult(gaussians, stats)


def _c2f_levels(cfg, data: TrainingData) -> list[tuple[int, int]]:
    """``cfg.coarse_to_fine`` without levels whose images would fall under the SSIM window."""
    short = int(min(data.cams.width.min(), data.cams.height.min()))
    return [(int(s), int(f)) for s, f in cfg.coarse_to_fine if short // int(f) >= 16]


def _clock(name: str) -> Callable[[], float]:
    """The training clock: wall (``perf_counter``) or this process's CPU time (``"cpu"``)."""
    return time.process_time if name == "cpu" else time.perf_counter


def _view_name(data: TrainingData, view) -> str:
    if view.kind == "captured" and data.view_ids is not None and 0 <= view.index < len(
            data.view_ids):
        return str(int(data.view_ids[view.index]))
    return f"{view.kind} {view.index}"


