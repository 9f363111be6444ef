"""The engine's fixer inside refine-3dgs (docs/REFINE.md "Fixed arms").

:class:`SceneFixer` renders a camera from a set of Gaussians (the store's reconstruction of
the training part, or the model being trained), warps the ``k`` nearest *training* photos
into it with the rendered depths (the reproject warp the fixer was trained with) and runs the
fixer network (:mod:`freescale_core.fixer`). It returns the fixed image, the fixer's
per-pixel confidence and the observed map (render alpha, or a valid warp), so a loss can
weight each pixel by ``confidence x observed``: a region neither the reconstruction nor any
photo saw teaches nothing.

Only training views are ever warped in: the held-out photos of a refine comparison never
reach a pseudo view or a post-fixed render.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from freescale_core.freeviews.references import pose_distances
from freescale_core.freeviews.rectify_image import FixerRectifier, RenderedView
from freescale_core.raster import render_gaussians
from freescale_core.recon.data import _to_gaussians
from freescale_core.recon.views import ViewCamera


def params_gaussians(state) -> object:
    """The trainer's current Gaussians (``TrainState``) at its current SH degree."""
    return _to_gaussians(state.params, int(getattr(state, "sh_degree", 0)))


class SceneFixer:
    """The fixer at any camera of one scene, with the training photos as references.

    Args:
        data: the comparison's :class:`~freescale_core.recon.trainer.TrainingData`
            (training cameras at the training resolution and their photos).
        checkpoint: a ``fixer.pt``; None = the shipped one.
        background: RGB behind the Gaussians in the renders.
        backend: rasterizer backend.
    """

    def __init__(self, data, checkpoint: str | None = None, background=(0.0, 0.0, 0.0),
                 backend: str = "auto") -> None:
        self.rect = FixerRectifier(checkpoint)
        self.data = data
        self.background = tuple(float(x) for x in background)
        self.backend = backend
        self.poses = np.asarray(data.cams.world_from_cam, np.float64)
        self.n_refs = int(self.rect.n_references)
        self._refs: dict[tuple[int, int], RenderedView] = {}
        self.seconds = 0.0  # wall time spent rendering, warping and fixing
        self.calls = 0

    # ------------------------------------------------------------------ renders
    def _render(self, g, wfc, fx, fy, cx, cy, w, h) -> RenderedView:
        rgb, depth, alpha = render_gaussians(g, wfc, fx, fy, cx, cy, int(w), int(h),
                                             background=self.background, backend=self.backend)
        return RenderedView(rgb, depth, alpha, np.asarray(wfc, np.float64), float(fx),
                            float(fy), float(cx), float(cy))

    def _reference(self, g, i: int, cache_key: int | None):
        c = self.data.cams
        key = (cache_key, i) if cache_key is not None else None
        view = self._refs.get(key) if key is not None else None
        if view is None:
            view = self._render(g, c.world_from_cam[i], c.fx[i], c.fy[i], c.cx[i], c.cy[i],
                                c.width[i], c.height[i])
            if key is not None:
                self._refs[key] = view
        img = self.data.images[i]
        photo = img.numpy() if isinstance(img, torch.Tensor) else np.asarray(img)
        if photo.dtype != np.uint8:
            photo = np.floor(np.clip(photo, 0, 1) * 255 + 0.5).astype(np.uint8)
        return photo[..., :3], view

    def forget(self, cache_key: int) -> None:
        """Drop the reference renders cached under ``cache_key``."""
        self._refs = {k: v for k, v in self._refs.items() if k[0] != cache_key}

    # ------------------------------------------------------------------ fixing
    def fix(self, g, cam: ViewCamera, cache_key: int | None = None) -> dict:
        """Fix the render of ``g`` at ``cam``.

        Args:
            g: :class:`~freescale_core.scene.gaussians.Gaussians`.
            cam: the camera (its size is the output's).
            cache_key: reference renders of ``g`` are cached under this key (pass one for a
                model that does not change, None for the model being trained).
        Returns:
            ``{"image": uint8 [H, W, 3], "render": uint8, "confidence": float32 [H, W],
            "observed": float32 [H, W] in [0, 1], "coverage": fraction of pixels a warp
            covers, "refs": training indices warped in}``.
        """
        t0 = time.perf_counter()
        view = self._render(g, cam.world_from_cam, cam.fx, cam.fy, cam.cx, cam.cy, cam.width,
                            cam.height)
        order = np.argsort(pose_distances(self.poses, cam.world_from_cam), kind="stable")
        refs = [int(i) for i in order[: self.n_refs]]
        pairs = [self._reference(g, i, cache_key) for i in refs]
        warps, weight = self.rect.warps(view, [p for p, _ in pairs], [v for _, v in pairs])
        fixed, conf = self.rect.fix([view], warps[None], weight[None])
        warped = weight.max(axis=0) > 0 if len(weight) else np.zeros(view.hw, bool)
        observed = np.maximum(np.clip(view.alpha, 0.0, 1.0), warped.astype(np.float32))
        out = {"image": _u8(fixed[0]), "render": _u8(view.rgb),
               "confidence": np.clip(conf[0], 0.0, 1.0).astype(np.float32),
               "observed": observed.astype(np.float32),
               "coverage": float(warped.mean()), "refs": refs}
        self.seconds += time.perf_counter() - t0
        self.calls += 1
        return out


def _u8(rgb: np.ndarray) -> np.ndarray:
    return np.floor(np.clip(np.asarray(rgb, np.float32), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
