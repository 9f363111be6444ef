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
