"""Plug-ins of the training loop that schedule it: the SH degree and when to stop.

Like the densification :mod:`~freescale_core.recon.strategy`, each is an object the loop in
:func:`freescale_core.recon.trainer.train` calls at fixed points of a step; the loop itself
only draws views, renders, takes the loss and steps Adam.

* :class:`SHSchedule`: the degree at each step (+1 every ``sh_increase_every`` up to the
  degree :func:`~freescale_core.recon.sizing.choose_sh_degree` allows; the exposure spread of
  the training views caps it where ``sh_cap_min_gain_std`` asks);
* :class:`Stopping`: the training progress ``p`` the learning rates read, the loss EMA, and
  the plateau / anneal / time rule: the first plateau while the strategy grows stops growth,
  the next one (or the time budget less the annealing) starts ``anneal_fraction`` of the steps
  so far of final annealing, after which training stops.
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from freescale_core.recon.sizing import choose_sh_degree, plateau_reached


def _wants_gain_spread(cfg) -> bool:
    """Whether a rule of ``cfg`` reads the training views' colour gain spread."""
    return cfg.sh_views_per_coeff is not None and cfg.sh_cap_min_gain_std is not None


def _gain_spread(data) -> tuple[float | None, str]:
    """The std over the training views of their log colour gains, measured on the scene's own
    sparse points (:mod:`freescale_core.recon.photometric`), None when too few views see
    enough usable points; and what it was measured on."""
    from freescale_core.recon.photometric import gain_spread, view_log_gains

    n = data.n_own_points
    g = view_log_gains(data.cams, data.images, data.points_xyz[:n], data.points_rgb[:n])
    return gain_spread(g), f"{int(np.isfinite(g).all(1).sum())} of {len(g)} views, {n} sparse points"


def anneal_threshold(cfg) -> float:
    """Budget seconds at which the annealing starts: the budget less ``anneal_fraction`` of the
    time before it."""
    return cfg.max_seconds / (1.0 + cfg.anneal_fraction)


class SHSchedule:
    """The SH degree per step; ``gain_std`` (the views' exposure spread) is measured only when
    the SH cap reads it."""

    def __init__(self, cfg, data):
        self.cfg = cfg
        self.gain_std, _ = _gain_spread(data) if _wants_gain_spread(cfg) else (None, "")
        self.max_degree, self.why = choose_sh_degree(len(data.images), cfg, self.gain_std)

    def degree(self, step: int) -> int:
        return min(self.max_degree, (step - 1) // self.cfg.sh_increase_every)

    def reason(self, step: int) -> str:
        return (f"degree {self.degree(step)} reached at step {step} "
                f"(+1 every {self.cfg.sh_increase_every}, {self.why})")


class Stopping:
    """Training progress, the loss EMA and the plateau / anneal / time rule.

    Per step the loop calls :meth:`progress` (before the learning rates) and, after the
    optimiser, :meth:`after_step` with the step's photometric loss, which returns whether this
    is the last step; ``elapsed()`` is the training clock (checkpoints excluded)."""

    def __init__(self, cfg, n_train: int, c2f_levels, elapsed: Callable[[], float]):
        self.cfg = cfg
        self.elapsed = elapsed
        halflife = max(cfg.plateau_ema_halflife, 2.0 * n_train)
        self.beta = 0.5 ** (1.0 / halflife)
        # The EMA is one view's loss at step 1 and needs about a half-life to average the
        # views; a window shorter than the half-life cannot see an improvement through the
        # EMA's lag. Without these two guards a 34-view scene (half-life 68) "plateaued" at
        # step 62 of the fast preset (window 60) at 10 dB (dtu_scan24, OOD split).
        warmup = int(math.ceil(halflife))
        self.window = max(cfg.plateau_window, warmup)
        # A coarse-to-fine level's loss (smoother, smaller images) is lower than the full
        # resolution's, so a window reaching back across the last switch compares unlike
        # losses and reads a plateau that is not there: llff_fern's cpu preset (switch at step
        # 600) "plateaued" at step 1000 and stopped growing at 23.6k of its 64.7k Gaussians.
        # The window starts after the last switch and the EMA's warm-up past it.
        self.plateau_from = warmup + max((s for s, _ in c2f_levels), default=0)
        self.ema_m = self.ema_w = 0.0
        self.ema_hist: list[float] = []
        self.last_event = 0
        self.anneal_start: int | None = None
        self.anneal_len = 0
        self.anneal_p0 = 0.0
        self.p = 0.0
        self.stop_reason = f"max_iterations {cfg.max_iterations} reached"
        self.history: list[tuple[int, float, int]] = []
        self.loss_first = None

    @property
    def annealing(self) -> bool:
        return self.anneal_start is not None

    def progress(self, step: int) -> float:
        """Training progress in [0, 1] for the learning-rate schedules (the annealing runs the
        rest of it over its steps)."""
        cfg = self.cfg
        if self.anneal_start is None:
            self.p = step / cfg.max_iterations
        else:
            self.p = self.anneal_p0 + (1 - self.anneal_p0) * (step - self.anneal_start) / max(
                self.anneal_len, 1)
        return self.p

    def after_step(self, step: int, photo: float, n_now: int, strategy, state,
                   reasons: dict, budget: int) -> bool:
        cfg = self.cfg
        self.loss_first = photo if self.loss_first is None else self.loss_first
        self.ema_m = self.beta * self.ema_m + (1 - self.beta) * photo
        self.ema_w = self.beta * self.ema_w + (1 - self.beta)
        self.ema_hist.append(self.ema_m / self.ema_w)
        if step % max(1, cfg.max_iterations // 200) == 0 or step == 1:
            self.history.append((step, self.ema_hist[-1], n_now))
        stopping = False
        window = self.window
        if self.anneal_start is None:
            event = None
            if (step >= cfg.min_iterations and step - self.last_event >= window
                    and step - window >= self.plateau_from
                    and plateau_reached(self.ema_hist, window, cfg.plateau_tol)):
                event = "plateau"
            elif cfg.max_seconds is not None and self.elapsed() >= anneal_threshold(cfg):
                event = "time"  # leave room for the annealing inside the budget
            if event == "plateau" and strategy.on_plateau(state, step) is not None:
                self.last_event = step
                reasons["growth_stop"] = (
                    f"loss EMA improved < {cfg.plateau_tol:.0%} over {window} steps "
                    f"at step {step} with {n_now} Gaussians (budget {budget}): growth stopped")
            elif event is not None:
                self.anneal_start, self.anneal_p0 = step, self.p
                anneal_len = max(1, int(round(cfg.anneal_fraction * step)))
                self.anneal_len = min(anneal_len, cfg.max_iterations - step)
                why = (f"loss EMA improved < {cfg.plateau_tol:.0%} over {window} "
                       f"steps at step {step}" if event == "plateau"
                       else f"{anneal_threshold(cfg):.0f} s of the time "
                       f"budget {cfg.max_seconds:g} s used at step {step}")
                self.stop_reason = f"{why}; then {self.anneal_len} annealing steps"
                stopping = self.anneal_len == 0
        elif step - self.anneal_start >= self.anneal_len:
            stopping = True
        elif cfg.max_seconds is not None and self.elapsed() >= cfg.max_seconds:
            self.stop_reason += f" (cut at step {step}: time budget {cfg.max_seconds:g} s)"
            stopping = True
        return stopping

    def loss_stats(self) -> dict:
        h = self.ema_hist
        return {"first": self.loss_first, "final_ema": h[-1] if h else None,
                "min_ema": float(min(h)) if h else None,
                "history": [[s, float(e), int(n)] for s, e, n in self.history]}
