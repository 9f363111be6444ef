"""LVSM evaluation regimes on held-out procedural scenes (truth from the oracle).

Three regimes, defined by the numbers of :class:`schemas.lvsm.LVSMEvalConfig`:

* ``small``: inputs spread over a short window of the capture (``small_span`` frames), the
  target a captured frame strictly between them (interpolation, small motion);
* ``large``: inputs over ``large_span`` frames, the target ``extrap_frames`` further along the
  path, after the last input or before the first (extrapolation along the path);
* ``offpath``: the target is a pose the capture never visited
  (:func:`freescale_core.scene.family.off_path_poses`: other heights, radii, looking across), its truth
  rendered by the oracle at the capture's size and downsampled like the training images;
  inputs span ``offpath_span`` frames around the capture frame nearest the target.

Each example has one target. Beside the model two baselines: ``copy_nearest`` (the input
whose camera is nearest the target: centre distance plus 0.5 m per radian of viewing-axis
angle) and ``mean_inputs`` (per-pixel mean of the inputs). Metrics: PSNR (dB, images in
[0, 1]) and SSIM (11x11 Gaussian window, :func:`freescale_core.recon.losses.ssim`), averaged
over examples. The examples are built once (:func:`build_examples`, deterministic for the
config's seed) so several models are scored on the very same ones.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from freescale_core.downstream.lvsm.data import (
    SceneTensors,
    load_sample_scene,
    resize_views,
)
from freescale_core.recon.losses import ssim as ssim_torch
from freescale_core.scene.family import off_path_poses
from schemas.lvsm import LVSMEvalConfig

__all__ = [
    "METHODS",
    "REGIMES",
    "EvalScene",
    "Example",
    "build_examples",
    "evaluate",
    "load_eval_scene",
    "nearest_input",
]

REGIMES = ("small", "large", "offpath")
METHODS = ("model", "copy_nearest", "mean_inputs")


@dataclass
class EvalScene:
    """A held-out scene: its captured views as tensors plus its oracle."""

    tensors: SceneTensors
    scene_dir: Path

    @property
    def world(self):
        from freescale_core.scene.sample import SampleWorld

        if not hasattr(self, "_world"):
            self._world = SampleWorld.load(self.scene_dir)
        return self._world


@dataclass
class Example:
    """One evaluation example: input view ids and one target camera with its truth."""

    scene: EvalScene
    regime: str
    input_ids: np.ndarray  # [Vi] ids into scene.tensors
    tgt_c2w: torch.Tensor  # [4, 4] float64
    tgt_K: torch.Tensor  # [4] float64
    truth: torch.Tensor  # [3, H, W] float32 in [0, 1]


def load_eval_scene(scene_dir: str | Path, width: int, height: int) -> EvalScene:
    """A sample-scene folder as a held-out scene at ``width x height``."""
    return EvalScene(load_sample_scene(scene_dir, width, height), Path(scene_dir))


def _spread(start: int, span: int, k: int) -> np.ndarray:
    """``k`` distinct frame positions spread evenly over ``[start, start + span]``."""
    pos = np.round(np.linspace(start, start + span, k)).astype(np.int64)
    return np.unique(pos) if len(np.unique(pos)) == k else start + np.arange(k)


def nearest_input(in_c2w: torch.Tensor, tgt_c2w: torch.Tensor) -> int:
    """Index of the input camera ``[Vi, 4, 4]`` nearest the target ``[4, 4]``: centre
    distance + 0.5 m per radian between viewing axes."""
    d = torch.linalg.vector_norm(in_c2w[:, :3, 3] - tgt_c2w[:3, 3], dim=-1)
    cos = (in_c2w[:, :3, 2] * tgt_c2w[:3, 2]).sum(-1).clamp(-1, 1)
    return int(torch.argmin(d + 0.5 * torch.arccos(cos)))


def build_examples(scenes: list[EvalScene], cfg: LVSMEvalConfig | None = None
                   ) -> dict[str, list[Example]]:
    """The examples of every regime (``cfg.n_per_scene`` per scene), deterministic.

    Raises:
        ValueError: a capture too short for a regime's window (names the scene).
    """
    cfg = cfg or LVSMEvalConfig()
    out: dict[str, list[Example]] = {r: [] for r in REGIMES}
    for si, es in enumerate(scenes):
        sc = es.tensors
        order = sc.views.captured_order
        n = len(order)
        name = f"scene {sc.scene_id!r}"
        need = max(cfg.small_span, cfg.large_span + cfg.extrap_frames[1]) + 1
        if n < need:
            raise ValueError(f"{name}: {n} captured views; the regimes need >= {need}")
        rng = np.random.default_rng([cfg.seed, si])
        H, W = sc.hw

        def ex(regime, pos_in, tgt_id=None, c2w=None, K=None, truth=None, sc=sc, es=es,
               order=order):
            if tgt_id is not None:
                c2w, K, truth = sc.world_from_cam[tgt_id], sc.K[tgt_id], sc.images[tgt_id]
            out[regime].append(Example(es, regime, order[pos_in], c2w, K, truth))

        for _ in range(cfg.n_per_scene):
            s = int(rng.integers(0, n - cfg.small_span))
            pos = _spread(s, cfg.small_span, cfg.n_input)
            between = np.setdiff1d(np.arange(pos[0] + 1, pos[-1]), pos)
            ex("small", pos, tgt_id=order[int(rng.choice(between))])

            off = int(rng.integers(cfg.extrap_frames[0], cfg.extrap_frames[1] + 1))
            s = int(rng.integers(0, n - cfg.large_span - off))
            if rng.random() < 0.5:  # target after the inputs
                pos, t = _spread(s, cfg.large_span, cfg.n_input), s + cfg.large_span + off
            else:  # target before the inputs
                pos, t = _spread(s + off, cfg.large_span, cfg.n_input), s
            ex("large", pos, tgt_id=order[t])

        world = es.world
        cams = off_path_poses(world, cfg.n_per_scene, seed=cfg.seed + si,
                              min_distance=cfg.offpath_min_distance)
        centers = sc.world_from_cam[order, :3, 3].numpy()
        for k in range(len(cams)):
            rgb, _ = world.render_camera(cams, k)
            K0 = np.array([[cams.fx[k], cams.fy[k], cams.cx[k], cams.cy[k]]])
            img, K = resize_views(rgb[None], K0, W, H)
            near = int(np.argmin(np.linalg.norm(centers - cams.centers[k], axis=1)))
            s = int(np.clip(near - cfg.offpath_span // 2, 0, n - 1 - cfg.offpath_span))
            ex("offpath", _spread(s, cfg.offpath_span, cfg.n_input),
               c2w=torch.as_tensor(cams.world_from_cam[k], dtype=torch.float64),
               K=torch.as_tensor(K[0]), truth=torch.from_numpy(img[0]))
    return out


def _metrics(pred: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    mse = float((pred - truth).square().mean())
    p = -10.0 * np.log10(max(mse, 1e-10))
    s = float(ssim_torch(pred.permute(1, 2, 0).double(), truth.permute(1, 2, 0).double()))
    return p, s


@torch.no_grad()
def evaluate(model, examples: dict[str, list[Example]], batch_size: int = 8,
             device: str = "cpu", baselines: bool = True) -> dict[str, dict[str, dict]]:
    """PSNR / SSIM per regime and method.

    Args:
        model: an LVSM (or None: baselines only).
    Returns:
        ``{regime: {method: {"psnr": mean, "ssim": mean, "n": count}}}``.
    """
    res: dict[str, dict[str, dict]] = {}
    if model is not None:
        was = model.training
        model.eval()
    for regime, exs in examples.items():
        scores: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
        for i in range(0, len(exs), batch_size):
            chunk = exs[i:i + batch_size]
            imgs = torch.stack([e.scene.tensors.images[torch.as_tensor(e.input_ids)]
                                for e in chunk])  # [B, Vi, 3, H, W]
            in_c2w = torch.stack([e.scene.tensors.world_from_cam[torch.as_tensor(e.input_ids)]
                                  for e in chunk])
            in_K = torch.stack([e.scene.tensors.K[torch.as_tensor(e.input_ids)] for e in chunk])
            tgt_c2w = torch.stack([e.tgt_c2w for e in chunk])[:, None]
            tgt_K = torch.stack([e.tgt_K for e in chunk])[:, None]
            if model is not None:
                dev = torch.device(device)
                pred = model(imgs.to(dev), in_c2w.to(dev), in_K.to(dev), tgt_c2w.to(dev),
                             tgt_K.to(dev))[:, 0].float().cpu()
            for b, e in enumerate(chunk):
                if model is not None:
                    scores["model"].append(_metrics(pred[b], e.truth))
                if baselines:
                    j = nearest_input(in_c2w[b], e.tgt_c2w)
                    scores["copy_nearest"].append(_metrics(imgs[b, j], e.truth))
                    scores["mean_inputs"].append(_metrics(imgs[b].mean(0), e.truth))
        res[regime] = {m: {"psnr": float(np.mean([v[0] for v in s])),
                           "ssim": float(np.mean([v[1] for v in s])), "n": len(s)}
                       for m, s in scores.items() if s}
    if model is not None:
        model.train(was)
    return res
