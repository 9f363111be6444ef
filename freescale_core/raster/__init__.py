"""Differentiable 3D Gaussian Splatting rasterizer (CPU-first; gsplat on CUDA).

METHOD.md stage 1 (reconstruct: the trainer renders and back-propagates through this) and
stage 7 (render RGB + depth of the selected free views). Model: standard 3DGS EWA splatting;
the exact rules (near plane, +0.3 px low-pass, 3-sigma extent, alpha clamp/skip, early
termination, SH colour) are in ``_common.py`` and ``docs/RASTERIZER.md``.

Backends:
    ``"cpu"``: tile-based numba kernels with a hand-written backward (``cpu.py``).
    ``"gsplat"``: ``gsplat.rasterization`` when CUDA and gsplat are present (``gsplat_backend.py``).
    ``"reference"``: dense pure-torch autograd (``reference.py``), slow; the test oracle.
    ``"auto"``: gsplat when usable and the tensors live on CUDA, else cpu.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .reference import rasterize_reference


@dataclass
class RenderOutput:
    """One rendered view.

    Attributes:
        rgb: ``[H, W, 3]`` float32, composited over the background.
        depth: ``[H, W]`` float32 expected camera-z depth normalised by alpha,
            ``sum_i w_i z_i / alpha`` (0 where alpha < 1e-6).
        alpha: ``[H, W]`` float32 accumulated opacity ``1 - T_final``.
    """

    rgb: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor


def _gsplat_usable(tensor: torch.Tensor) -> bool:
    if not (torch.cuda.is_available() and tensor.is_cuda):
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def rasterize(means, log_scales, quats_wxyz, opacity_logits, sh,
              world_from_cam, fx, fy, cx, cy, width, height,
              sh_degree: int | None = None, background=(0.0, 0.0, 0.0),
              backend: str = "auto", exact_tiles: bool = True) -> RenderOutput:
    """Render N Gaussians into one pinhole view; differentiable w.r.t. all five tensors.

    Args:
        means: ``[N, 3]`` world centres. log_scales: ``[N, 3]`` log std-devs.
        quats_wxyz: ``[N, 4]`` rotations (normalised inside). opacity_logits: ``[N]``.
        sh: ``[N, K, 3]`` SH coefficients, K = (deg + 1)^2, deg <= 3.
        world_from_cam: ``[4, 4]`` camera-to-world (np or torch), OpenCV axes.
        fx, fy, cx, cy: pinhole intrinsics in pixels (top-left pixel centre at 0.5, 0.5).
        width, height: image size in pixels.
        sh_degree: use the first (sh_degree + 1)^2 coefficients; None = all.
        background: RGB composited behind (constant, no gradient).
        backend: "auto" | "cpu" | "gsplat" | "reference".
        exact_tiles: cpu backend: skip the bounding-box tiles the Gaussian's ellipse misses
            (identical output; 23-29% less raster time on two trained scenes, see
            docs/RASTERIZER.md); False = the older binning, kept to measure the old trainer.
            Ignored by the other backends.
    Returns:
        :class:`RenderOutput` (float32 for cpu/gsplat).
    """
    if backend == "auto":
        backend = "gsplat" if _gsplat_usable(means) else "cpu"
    args = (means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
            fx, fy, cx, cy, width, height)
    if backend == "reference":
        return rasterize_reference(*args, sh_degree=sh_degree, background=background)
    if backend == "cpu":
        from .cpu import rasterize_cpu

        return rasterize_cpu(*args, sh_degree=sh_degree, background=background,
                             exact_tiles=exact_tiles)
    if backend == "gsplat":
        from .gsplat_backend import rasterize_gsplat

        return rasterize_gsplat(*args, sh_degree=sh_degree, background=background)
    raise ValueError(f"unknown backend {backend!r}; expected auto, cpu, gsplat or reference")


def render_gaussians(g, world_from_cam, fx, fy, cx, cy, width, height,
                     background=(0.0, 0.0, 0.0), backend: str = "auto",
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """No-grad numpy convenience for rendering a :class:`~freescale_core.scene.gaussians.Gaussians`.

    Returns:
        ``(rgb [H, W, 3] float32 clipped to [0, 1], depth [H, W] float32, alpha [H, W] float32)``.
    """
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    with torch.no_grad():
        out = rasterize(t(g.means), t(g.log_scales), t(g.quats_wxyz), t(g.opacity_logits),
                        t(g.sh), world_from_cam, fx, fy, cx, cy, width, height,
                        background=background, backend=backend)
    rgb = np.clip(out.rgb.detach().cpu().numpy(), 0.0, 1.0).astype(np.float32)
    return (rgb, out.depth.detach().cpu().numpy().astype(np.float32),
            out.alpha.detach().cpu().numpy().astype(np.float32))


def render_gaussians_batch(g, world_from_cam, fx, fy, cx, cy, width, height,
                           background=(0.0, 0.0, 0.0), backend: str = "auto",
                           ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`render_gaussians` over ``N`` cameras in one call, same output per view.

    The cpu backend converts the Gaussians once and calls the forward kernels directly (no
    autograd graph, no saved backward state); other backends render view by view.

    Args:
        g: :class:`~freescale_core.scene.gaussians.Gaussians`.
        world_from_cam: ``[N, 4, 4]`` camera-to-world, OpenCV axes.
        fx, fy, cx, cy: ``[N]`` intrinsics in pixels; width, height: ``[N]`` image sizes.
    Returns:
        ``N`` tuples ``(rgb [H, W, 3] float32 in [0, 1], depth [H, W], alpha [H, W])``, equal
        bit for bit to :func:`render_gaussians` of each camera (tested).
    """
    poses = np.asarray(world_from_cam, np.float64).reshape(-1, 4, 4)
    n = len(poses)
    intr = [np.broadcast_to(np.asarray(a, np.float64).ravel(), (n,))
            for a in (fx, fy, cx, cy, width, height)]
    if backend == "auto":
        backend = "cpu"  # numpy Gaussians live on the host: auto picks cpu (see rasterize)
    if backend != "cpu":
        return [render_gaussians(g, poses[i], *(float(a[i]) for a in intr[:4]),
                                 int(intr[4][i]), int(intr[5][i]), background, backend)
                for i in range(n)]
    from . import _common as c
    from .cpu import camera_vector, forward_numpy

    arrs = [np.ascontiguousarray(np.asarray(a), dtype=np.float32)
            for a in (g.means, g.log_scales, g.quats_wxyz, g.opacity_logits, g.sh)]
    _, deg = c.check_inputs(*(torch.from_numpy(a) for a in arrs), None)
    bg = np.asarray(c.background_tuple(background), np.float32)
    out = []
    for i in range(n):
        w, h = int(intr[4][i]), int(intr[5][i])
        cam = camera_vector(poses[i], *(float(a[i]) for a in intr[:4]), w, h)
        rgb, depth, alpha, _ = forward_numpy(*arrs, deg, cam, w, h, bg)
        out.append((np.clip(rgb, 0.0, 1.0).astype(np.float32), depth.astype(np.float32),
                    alpha.astype(np.float32)))
    return out


__all__ = ["RenderOutput", "rasterize", "rasterize_reference", "render_gaussians",
           "render_gaussians_batch"]
