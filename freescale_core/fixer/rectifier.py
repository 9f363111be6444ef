"""The ``fixer`` image rectifier: the trained network applied to a free view.

Inputs per view: its render (RGB + alpha) and the stage's reference photos warped into it
with the rendered depths (:meth:`ReprojectRectifier.warp`); output: the corrected image and,
as the result's ``weight``, the fixer's per-pixel confidence in (0, 1). The depth is the
render's (the fixer changes colours only).

Checkpoint: ``params.checkpoint`` names a ``fixer.pt`` (``freescale train-fixer``); without
it the checkpoint shipped with the package (``freescale_core/data/fixer.pt``, see
docs/FIXER.md for the command that made it). A missing or mismatched checkpoint is a
:class:`~freescale_core.fixer.model.FixerCheckpointError` naming the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

from freescale_core.freeviews.rectify_image import (RectifyResult, RenderedView,
                                                    ReprojectRectifier)

__all__ = ["FixerRectifier", "shipped_checkpoint"]


def shipped_checkpoint() -> Path:
    """The fixer checkpoint shipped with the package."""
    return Path(__file__).resolve().parents[1] / "data" / "fixer.pt"


class FixerRectifier:
    """Stage-10 backend running a trained fixer (see the module docstring).

    Args:
        checkpoint: path of a ``fixer.pt``; None = the shipped one.
        batch_size: views per forward pass when several are fixed at once.
        **warp: parameters of the reproject warp (``ReprojectRectifier``'s), as in training.
    """

    name = "fixer"
    needs_reference = True

    def __init__(self, checkpoint: str | None = None, batch_size: int = 8,
                 **warp: Any) -> None:
        from freescale_core.fixer.model import load_fixer

        self.checkpoint = str(checkpoint or shipped_checkpoint())
        self.model, self.meta = load_fixer(self.checkpoint)
        self.k = int(self.model.cfg.k)
        self.n_references = max(1, self.k)  # the stage hands this many references
        self.batch_size = int(batch_size)
        self.warper = ReprojectRectifier(**warp)

    def warps(self, view: RenderedView, ref_photos: Sequence[np.ndarray | None],
              ref_renders: Sequence[RenderedView | None]) -> tuple[np.ndarray, np.ndarray]:
        """``(warps [k, H, W, 3], weight [k, H, W])``, zero where a warp gives no evidence."""
        H, W = view.hw
        warps = np.zeros((self.k, H, W, 3), np.float32)
        weight = np.zeros((self.k, H, W), np.float32)
        slot = 0
        for photo, ref in zip(ref_photos, ref_renders):
            if slot >= self.k:
                break
            if photo is None or ref is None:
                continue
            e = self.warper.warp(view, photo, ref)
            w = e["weight"]
            warps[slot] = np.where(w[..., None] > 0, e["warped"], 0.0)
            weight[slot] = w
            slot += 1
        return warps, weight

    def fix(self, views: Sequence[RenderedView], warps: np.ndarray, weight: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
        """Fix N views of one size: ``(fixed [N, H, W, 3], conf [N, H, W])``."""
        from freescale_core.fixer.infer import fix_views

        rgb = np.stack([np.asarray(v.rgb, np.float32) for v in views])
        alpha = np.stack([np.ones(v.hw, np.float32) if v.alpha is None
                          else np.asarray(v.alpha, np.float32) for v in views])
        return fix_views(self.model, rgb, alpha, warps, weight, batch_size=self.batch_size)

    def __call__(self, view: RenderedView, ref_photo, ref_render) -> RectifyResult:
        photos = ref_photo if isinstance(ref_photo, (list, tuple)) else [ref_photo]
        renders = ref_render if isinstance(ref_render, (list, tuple)) else [ref_render]
        warps, weight = self.warps(view, photos, renders)
        fixed, conf = self.fix([view], warps[None], weight[None])
        H, W = view.hw
        depth = (np.zeros((H, W), np.float32) if view.depth is None
                 else np.asarray(view.depth, np.float32).copy())
        info = {"mean_confidence": float(conf[0].mean()),
                "warp_coverage": float((weight.max(axis=0) > 0).mean()) if self.k else 0.0,
                "n_references": int(sum(p is not None for p in photos))}
        return RectifyResult(fixed[0], depth, conf[0].astype(np.float32), info)
