"""Adam over the trainer's parameter dict, with per-row moment resets for densification."""

from __future__ import annotations

import numpy as np
import torch



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
