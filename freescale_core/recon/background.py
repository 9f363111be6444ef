"""The learned background colour behind unmasked photos (``ReconConfig.background_lr``)."""

from __future__ import annotations

import torch

from freescale_core.recon.sizing import exp_decay
from freescale_core.scene.gaussians import Gaussians
from schemas.recon import ReconConfig



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


class BackgroundPlugin:
    """The colour behind every training render, as a plug-in of the loop.

    Fixed (``cfg.background``) unless ``cfg.background_lr`` is set and the capture has no
    object masks: then a :class:`_Background` is learned, and ``background_min_uncovered``
    (the gate) decides at ``background_gate_step`` K whether to keep it, from the share of
    training pixels the Gaussians leave to it (alpha < 0.5) over steps (K/2, K]; below the
    threshold the colour goes back to ``cfg.background``, fixed.

    Hooks, in the order the loop calls them in a step: :meth:`set_progress` (with the
    learning-rate schedule), per view :meth:`for_view` (what the rasterizer draws behind) and
    :meth:`composite`, after the optimiser :meth:`after_optimizer`; at the end
    :meth:`finish`. :meth:`colour` is the colour now (checkpoints, held-out renders)."""

    def __init__(self, cfg, data, reasons: dict):
        self.cfg = cfg
        self.fixed = tuple(float(v) for v in cfg.background)
        bg = self.fixed
        self.learned = None
        if cfg.background_lr is not None:
            if data.masks is None:
                self.learned = _Background(bg, cfg.background_lr, cfg.background_lr_final)
                reasons["background"] = (
                    f"learned behind unmasked photos from {bg} "
                    f"(background_lr {cfg.background_lr:g}"
                    + ("" if cfg.background_lr_final is None else
                       f", decaying to {cfg.background_lr_final:g} with the means'")
                    + ")")
            else:
                reasons["background"] = (f"background_lr off: object masks, so {bg} behind "
                                         "every photo")
        self.gate_k = cfg.background_gate_step if (self.learned is not None and
                                                   cfg.background_min_uncovered is not None) \
            else None
        self.gate_sum = self.gate_n = 0.0
        self.uncovered_share = None

    def set_progress(self, p: float) -> None:
        if self.learned is not None:
            self.learned.set_progress(p)

    def for_view(self, view) -> tuple[tuple[float, float, float], bool]:
        """``(colour the rasterizer draws behind, composite on the learned colour after)``."""
        if self.learned is not None and view.kind == "captured":
            return (0.0, 0.0, 0.0), True
        return self.fixed, False

    def composite(self, rgb: torch.Tensor, alpha: torch.Tensor, step: int) -> torch.Tensor:
        rgb = self.learned.composite(rgb, alpha)
        if self.gate_k is not None and step > self.gate_k // 2:
            self.gate_sum += float((alpha.detach() < 0.5).float().mean())
            self.gate_n += 1
        return rgb

    def after_optimizer(self, step: int, reasons: dict) -> None:
        if self.learned is None:
            return
        self.learned.step()
        if self.gate_k is not None and step == self.gate_k:
            cfg, bg = self.cfg, self.fixed
            self.uncovered_share = self.gate_sum / max(self.gate_n, 1.0)
            keep = self.uncovered_share >= cfg.background_min_uncovered
            reasons["background"] += (
                f"; {100 * self.uncovered_share:.2f}% of training pixels below alpha 0.5 over "
                f"steps {self.gate_k // 2 + 1}-{self.gate_k} "
                + ("kept it" if keep else f"< {100 * cfg.background_min_uncovered:g}%: "
                   f"back to {bg}, fixed, from step {self.gate_k}"))
            self.gate_k = None
            if not keep:
                self.learned = None

    def colour(self) -> tuple[float, float, float]:
        return self.fixed if self.learned is None else self.learned.colour()

    def finish(self, reasons: dict) -> tuple[float, float, float]:
        if self.gate_k is not None:  # the run ended before the gate's step: it did not decide
            reasons["background"] += (f"; the run ended before step {self.gate_k}: "
                                      "the gate kept it")
        return self.colour()

    def stats(self) -> dict:
        return {"background": list(self.colour()),
                "background_lr_end": self.learned.lr() if self.learned is not None else None,
                "background_uncovered_share": self.uncovered_share}
