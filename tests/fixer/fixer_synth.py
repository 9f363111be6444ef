"""Synthetic fixer pairs for the tests: the target is a smooth random image, the render a
blurred, shifted copy of it, warp 0 the target itself with a little noise (weight 1 on most
pixels: the render is correctable from it), warp 1 pure noise with weight 0."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from freescale_core.fixer.data import FixerSample, write_pair_folder


def _smooth(rng: np.random.Generator, H: int, W: int) -> np.ndarray:
    import torch
    import torch.nn.functional as F

    lo = torch.from_numpy(rng.random((1, 3, H // 8 + 2, W // 8 + 2), np.float32))
    img = F.interpolate(lo, size=(H, W), mode="bicubic", align_corners=False)[0]
    img = img + 0.15 * torch.from_numpy(rng.standard_normal((3, H, W)).astype(np.float32))
    return np.clip(img.permute(1, 2, 0).numpy(), 0, 1)


def _blur(a: np.ndarray, r: int = 2) -> np.ndarray:
    out = np.zeros_like(a)
    n = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            out += np.roll(a, (dy, dx), axis=(0, 1))
            n += 1
    return out / n


def make_sample(rng: np.random.Generator, scene: str, i: int, H: int, W: int) -> FixerSample:
    target = _smooth(rng, H, W)
    render = np.clip(np.roll(_blur(target), (1, 1), axis=(0, 1)) * 0.9 + 0.05, 0, 1)
    warp0 = np.clip(target + 0.02 * rng.standard_normal(target.shape), 0, 1)
    w0 = (rng.random((H, W)) > 0.1).astype(np.float32)
    warps = np.stack([warp0 * w0[..., None], rng.random((H, W, 3))])
    ww = np.stack([w0, np.zeros((H, W), np.float32)])
    return FixerSample(render=render, alpha=np.ones((H, W), np.float32),
                       depth=np.ones((H, W), np.float32), warps=warps, warp_weight=ww,
                       warp_angle=np.full((2, H, W), 5.0, np.float32), target=target,
                       mask=np.ones((H, W), bool),
                       meta=dict(pair_id=f"{scene}_{i:03d}", scene_id=scene, fold="every8",
                                 budget="final", view_index=i, view_name=f"v{i:03d}",
                                 height=H, width=W, k=2, source="synthetic",
                                 psnr_render=None, psnr_warp0=None, warp_coverage=0.9,
                                 alpha_mean=1.0))


def make_pairs(root: str | Path, scenes=("sa", "sb", "sc"), n: int = 3, H: int = 40,
               W: int = 48, seed: int = 0) -> Path:
    """A pairs folder: ``root/<scene>/every8/`` with ``n`` pairs per scene."""
    root = Path(root)
    for j, sc in enumerate(scenes):
        rng = np.random.default_rng([seed, j])
        write_pair_folder(root / sc / "every8", [make_sample(rng, sc, i, H, W) for i in range(n)],
                          key={"scene": sc, "synthetic": True, "seed": seed})
    return root
