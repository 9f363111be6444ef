"""Densification strategies: what happens to the set of Gaussians around each training step.

The trainer (:func:`freescale_core.recon.trainer.train`) owns the loop (views, loss, Adam,
learning rates, stopping); a :class:`Strategy` owns the Gaussian set. It is called at fixed
points of every step:

* ``step_pre_backward(state, step, info) -> extra loss or None``: regularisation terms added
  to the photometric loss before ``backward`` (MCMC: mean opacity and mean scale);
* ``on_plateau(state, step) -> reason or None``: the loss plateaued; a strategy that is still
  growing stops growth and returns why (the trainer then keeps training), otherwise the
  trainer starts its final annealing;
* ``step_post_backward(state, step, info)``: after the optimiser step (and the trainer's
  schedule decision for this step): position noise, relocation, growth. ``info`` has
  ``lr_means``, ``annealing`` (no topology changes) and ``stopping`` (last step).

``state`` is the trainer's :class:`TrainState` (``params`` dict, ``opt`` with ``reset_rows`` /
``append_rows``, ``rng`` numpy generator, ``gen`` torch generator); a strategy may replace
``state.params`` (growth appends rows). The split into hooks follows the usual structure of
Gaussian-splatting trainers (a default 3DGS strategy and an MCMC strategy behind one
interface), so another densification (e.g. 3DGS clone/split) can be added without copying
the loop.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from freescale_core.recon import densify as mcmc


class Strategy:
    """No densification: the initial set is optimised as is (``ReconConfig.densify='none'``);
    Gaussians that leave the scene are still relocated (:meth:`keep_in_bounds`)."""

    name = "none"

    def __init__(self, cfg=None):
        self.cfg = cfg

    def initialize(self, state: Any, budget: int) -> None:
        self.budget = budget

    @property
    def growing(self) -> bool:
        return False

    def step_pre_backward(self, state: Any, step: int, info: dict) -> torch.Tensor | None:
        return None

    def on_plateau(self, state: Any, step: int) -> str | None:
        return None

    def step_post_backward(self, state: Any, step: int, info: dict) -> None:
        self.keep_in_bounds(state, step, info)

    def stop_reason(self, state: Any) -> str:
        return "no densification"

    # ---- keeping Gaussians in the scene (freescale_core.recon.bounds)
    n_out: dict | None = None

    def keep_in_bounds(self, state: Any, step: int, info: dict) -> None:
        """Every ``cfg.bounds_every`` steps: relocate Gaussians that left the scene's bound or
        that fewer than ``cfg.prune_min_views`` training views see (MCMC relocation onto live
        Gaussians drawn by opacity; the count is kept)."""
        cfg = getattr(self, "cfg", None)
        bounds = getattr(state.data, "bounds", None)
        if (cfg is None or bounds is None or not cfg.bounds_every or info.get("stopping")
                or step % cfg.bounds_every != 0):
            return
        from freescale_core.recon.bounds import flag_outliers

        flags = flag_outliers(state.params, bounds, cfg.bounds_margin, None, None, None,
                              cfg.prune_min_views, getattr(state.data, "cams", None),
                              cfg.prune_min_views_size)
        rows = np.unique(np.concatenate(list(flags.values())))
        if not len(rows):
            return
        moved, src = mcmc.relocate_rows(state.params, rows, state.rng, cfg.mcmc_min_opacity,
                                        cfg.mcmc_max_copies)
        state.opt.reset_rows(np.concatenate([moved, src]))
        self.n_out = self.n_out or {}
        for k, v in flags.items():
            self.n_out[k] = self.n_out.get(k, 0) + int(len(v))

    def stats(self) -> dict:
        return {"relocated_out_of_bounds": self.n_out} if self.n_out else {}


class MCMCStrategy(Strategy):
    """3DGS-MCMC (see :mod:`freescale_core.recon.densify`): opacity/scale regularisation,
    position noise on near-transparent Gaussians, relocation of dead Gaussians onto live ones
    and growth towards the scene's budget (fast enough to reach it in ``mcmc_grow_steps``
    densifications); the first loss plateau while growing stops growth."""

    name = "mcmc"

    def __init__(self, cfg):
        self.cfg = cfg
        self.n_relocated = 0
        self.n_added = 0
        self.growth = 1.0
        self._growing = False
        self.growth_stop: str | None = None

    def initialize(self, state: Any, budget: int) -> None:
        self.budget = budget
        n_init = state.params["means"].shape[0]
        if budget > n_init:
            self.growth = max(self.cfg.mcmc_growth,
                              (budget / n_init) ** (1.0 / self.cfg.mcmc_grow_steps))
        self._growing = budget > n_init

    @property
    def growing(self) -> bool:
        return self._growing

    def _unit(self, state: Any) -> float:
        """World units per unit of the normalised scene 3DGS-MCMC's constants were set in
        (cameras at distance ~1 from their centre): ``extent / 1.1``, so the position noise and
        the scale regulariser act the same in a scene of any size."""
        return state.data.extent / 1.1

    def step_pre_backward(self, state: Any, step: int, info: dict) -> torch.Tensor | None:
        p = state.params
        return (self.cfg.mcmc_opacity_reg * torch.sigmoid(p["opacity_logits"]).mean()
                + self.cfg.mcmc_scale_reg / self._unit(state) * torch.exp(p["log_scales"]).mean())

    def on_plateau(self, state: Any, step: int) -> str | None:
        if not self._growing:
            return None
        self._growing = False
        return "growth stopped"

    def step_post_backward(self, state: Any, step: int, info: dict) -> None:
        cfg = self.cfg
        if cfg.mcmc_noise_lr > 0:
            # Eq. 10 in normalised units: lr (world) / unit, covariance / unit^2, back * unit
            mcmc.position_noise(state.params, cfg.mcmc_noise_lr * info["lr_means"]
                                / self._unit(state) ** 2, state.gen)
        self.keep_in_bounds(state, step, info)
        if info.get("stopping") or info.get("annealing"):
            return
        if not (cfg.densify_from <= step <= cfg.densify_until and step % cfg.densify_every == 0):
            return
        params, opt, rng = state.params, state.opt, state.rng
        n_now = params["means"].shape[0]
        dead, src = mcmc.relocate_dead(params, rng, cfg.mcmc_min_opacity, cfg.mcmc_max_copies)
        opt.reset_rows(np.concatenate([dead, src]))
        self.n_relocated += len(dead)
        if self._growing:
            target_n = min(self.budget, int(math.ceil(n_now * self.growth)))
            params, src = mcmc.grow(params, target_n - n_now, rng, cfg.mcmc_min_opacity,
                                    cfg.mcmc_max_copies)
            state.params = params
            opt.reset_rows(src)
            opt.append_rows(target_n - n_now)
            self.n_added += target_n - n_now
            if target_n >= self.budget:
                self._growing = False
                if self.growth_stop is None:
                    self.growth_stop = f"budget {self.budget} reached at step {step}"

    def stop_reason(self, state: Any) -> str:
        return (f"densification window ended with {state.params['means'].shape[0]} Gaussians")

    def stats(self) -> dict:
        return {"growth_factor": self.growth, "relocated": self.n_relocated,
                "added": self.n_added, **super().stats()}


def make_strategy(cfg) -> Strategy:
    """The strategy named by ``cfg.densify``."""
    if cfg.densify == "mcmc":
        return MCMCStrategy(cfg)
    if cfg.densify == "none":
        return Strategy(cfg)
    raise ValueError(f"unknown densification strategy {cfg.densify!r}")
