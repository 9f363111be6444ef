"""Where the trainer's views come from: a :class:`ViewSource` hands out one :class:`View`
(image, camera, loss weight, optional mask) per step.

:class:`CapturedViews` is the reconstruction's own source (the captured training views, one
seeded permutation per epoch, weight 1). :class:`ScheduledViews` adds extra views, e.g.
pseudo-ground-truth renders of a refinement stage, from a given step on, drawn with a given
probability and loss weight, without copying the training loop::

    extra = [View(image, cam, weight=2 * alpha, lambda_ssim=0.5)]   # alpha (L1 + (1 - SSIM))
    src = ScheduledViews(CapturedViews(data), extra, start_step=500, probability=0.25)
    train(data, cfg, seed, view_source=src)

The loss of a view is ``weight * ((1 - l) L1 + l (1 - SSIM))`` with ``l = view.lambda_ssim``
(default: ``cfg.lambda_ssim``), over the pixels where ``mask`` is true when a mask is given.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np
import torch


@dataclass
class ViewCamera:
    """A pinhole camera at the training resolution (camera-to-world ``[4, 4]``, OpenCV axes)."""

    world_from_cam: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass
class View:
    """One training view.

    Attributes:
        image: ``[H, W, 3]`` uint8 (or float in [0, 1]) tensor at the camera's size.
        camera: :class:`ViewCamera`.
        weight: loss weight of this view.
        mask: optional ``[H, W]`` bool tensor: only these pixels count.
        lambda_ssim: SSIM weight of this view's loss (None: the config's).
        index: the view's index in its source (captured views: position in the training set).
        kind: ``"captured"`` or a label of the extra source (e.g. ``"pseudo"``).
    """

    image: torch.Tensor
    camera: ViewCamera
    weight: float = 1.0
    mask: torch.Tensor | None = None
    lambda_ssim: float | None = None
    index: int = -1
    kind: str = "captured"

    def target(self) -> torch.Tensor:
        """The image as float32 in [0, 1]."""
        img = self.image
        return img.to(torch.float32) / 255.0 if img.dtype == torch.uint8 else img.to(torch.float32)


class ViewSource(Protocol):
    """Anything with ``next(step, rng) -> View``; ``rng`` is the trainer's numpy generator
    (draw from it, and only from it, so a seed fixes the whole run)."""

    def next(self, step: int, rng: np.random.Generator) -> View: ...


class CapturedViews:
    """The captured training views, a fresh seeded permutation every epoch, weight 1.

    ``coarse_to_fine``: ``((until_step, factor), ...)``: before ``until_step`` the views are
    served downscaled by ``factor`` (area filter, intrinsics scaled); after the last entry at
    the training resolution. Early steps fit the low frequencies at a fraction of the pixels.
    """

    def __init__(self, data, coarse_to_fine: Sequence[tuple[int, int]] = ()):
        self.data = data
        self._order = np.zeros(0, np.int64)
        self.levels = sorted((int(s), int(f)) for s, f in coarse_to_fine if int(f) > 1)
        self._cache: dict[int, tuple] = {}

    def __len__(self) -> int:
        return len(self.data.images)

    def factor(self, step: int) -> int:
        for until, f in self.levels:
            if step < until:
                return f
        return 1

    def _level(self, f: int):
        if f not in self._cache:
            import cv2

            cams = self.data.cams.scaled(1.0 / f)
            imgs = [torch.from_numpy(cv2.resize(im.numpy(), (int(cams.width[j]),
                                                             int(cams.height[j])),
                                                interpolation=cv2.INTER_AREA))
                    for j, im in enumerate(self.data.images)]
            masks = None
            if self._loss_masks() is not None:
                from freescale_core.scene.io.masks import resize_mask

                masks = [torch.from_numpy(resize_mask(m.numpy(), int(cams.width[j]),
                                                      int(cams.height[j])))
                         for j, m in enumerate(self._loss_masks())]
            self._cache[f] = (cams, imgs, masks)
        return self._cache[f]

    def _loss_masks(self):
        """The training data's object masks when the loss is restricted to them, else None."""
        return getattr(self.data, "masks", None) if getattr(self.data, "mask_loss", False) \
            else None

    def view(self, j: int, factor: int = 1) -> View:
        c, images, masks = ((self.data.cams, self.data.images, self._loss_masks())
                            if factor == 1 else self._level(factor))
        cam = ViewCamera(c.world_from_cam[j], float(c.fx[j]), float(c.fy[j]), float(c.cx[j]),
                         float(c.cy[j]), int(c.width[j]), int(c.height[j]))
        return View(images[j], cam, 1.0, None if masks is None else masks[j], None, j,
                    "captured")

    def next(self, step: int, rng: np.random.Generator) -> View:
        if len(self._order) == 0:
            self._order = rng.permutation(len(self))
        j, self._order = int(self._order[0]), self._order[1:]
        return self.view(j, self.factor(step))


class ScheduledViews:
    """A base source plus extra views: from ``start_step`` on, each step draws an extra view
    (uniformly) with probability ``probability``, else the base source's next view.

    The extra views' weights are their own (``View.weight``); ``extra`` may be changed between
    steps (``add``) so a refinement can add pseudo views as they are rendered.
    """

    def __init__(self, base: ViewSource, extra: Sequence[View] = (), start_step: int = 0,
                 probability: float = 0.5):
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"ScheduledViews: probability {probability} not in [0, 1]")
        self.base, self.extra = base, list(extra)
        self.start_step, self.probability = int(start_step), float(probability)

    def add(self, views: Sequence[View]) -> None:
        self.extra.extend(views)

    def next(self, step: int, rng: np.random.Generator) -> View:
        if self.extra and step >= self.start_step and self.probability > 0:
            if rng.random() < self.probability:
                return self.extra[int(rng.integers(len(self.extra)))]
        return self.base.next(step, rng)
