"""CPU backend: tile-based numba rasterizer wrapped in a ``torch.autograd.Function``.

METHOD.md stage 1 (reconstruct) trains through this; stage 7 renders with it. Kernels and the
pipeline are described in ``kernels.py``; the model in ``_common.py`` / ``docs/RASTERIZER.md``.
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numba
import numpy as np
import torch

from . import _common as c
from . import kernels as k


@dataclass
class ForwardState:
    """What the backward pass needs from the forward pass (numpy, float32 unless noted)."""

    inputs: tuple  # means [N,3], log_scales [N,3], quats [N,4], logits [N], sh [N,K,3]
    deg: int
    cam: np.ndarray  # [23] float64, see kernels.project_fwd
    width: int
    height: int
    tiles_x: int
    bg: np.ndarray  # [3]
    rect: np.ndarray  # [N, 4] int32
    order: np.ndarray  # [M] int64 visible Gaussians front to back
    records: np.ndarray  # [E, 12] tile-major blend records
    tile_off: np.ndarray  # [T + 1] int64
    tile_order: np.ndarray  # [T] int64
    g_off: np.ndarray  # [M + 1] int64
    pair_dst: np.ndarray  # [E] int64
    depth: np.ndarray  # [H, W]
    alpha: np.ndarray  # [H, W]
    t_final: np.ndarray  # [H, W]
    last: np.ndarray  # [H, W] int32


def camera_vector(world_from_cam, fx, fy, cx, cy, width, height) -> np.ndarray:
    """Pack the camera into the float64 ``[23]`` vector the kernels read."""
    R_cw, t_cw, centre = c.camera_from_pose(world_from_cam)
    fx, fy, cx, cy = float(fx), float(fy), float(cx), float(cy)
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lims = [(width - cx) / fx + c.FOV_CLAMP * tan_x, cx / fx + c.FOV_CLAMP * tan_x,
            (height - cy) / fy + c.FOV_CLAMP * tan_y, cy / fy + c.FOV_CLAMP * tan_y]
    return np.concatenate([R_cw.ravel(), t_cw, centre, [fx, fy, cx, cy], lims]).astype(np.float64)


def _np32(t: torch.Tensor) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float32)


# Below this much work the kernels run on one thread: a fork-join region costs a scheduler
# time slice whenever a worker thread is descheduled (a shared, loaded machine; OpenMP workers
# also spin-wait), which is more than a small render takes in total (docs/RASTERIZER.md).
SERIAL_MAX_GAUSSIANS = 50_000
SERIAL_MAX_PIXELS = 512 * 512
# Cap on numba threads for large renders (default: all of numba's). On a shared machine set it
# to 1 (or start Python with OMP_WAIT_POLICY=PASSIVE): see the benchmark in docs/RASTERIZER.md.
THREADS_ENV = "FREESCALE_RASTER_THREADS"


def _max_threads(current: int) -> int:
    """The caller's numba thread count, capped by ``$FREESCALE_RASTER_THREADS`` if set."""
    n = current
    cap = os.environ.get(THREADS_ENV, "").strip()
    if cap:
        try:
            n = max(1, min(n, int(cap)))
        except ValueError:
            raise ValueError(f"{THREADS_ENV}={cap!r}: expected a positive integer") from None
    return n


@contextmanager
def _threads_for(n_gaussians: int, n_pixels: int):
    """One numba thread for small problems, else the caller's count (capped); restored on exit.

    The caller's ``numba.set_num_threads`` is respected as an upper bound.
    """
    small = n_gaussians <= SERIAL_MAX_GAUSSIANS and n_pixels <= SERIAL_MAX_PIXELS
    prev = numba.get_num_threads()
    numba.set_num_threads(1 if small else _max_threads(prev))
    try:
        yield
    finally:
        numba.set_num_threads(prev)


def _balanced_tile_order(cost: np.ndarray, n_threads: int) -> np.ndarray:
    """Tile processing order for numba's static schedule (contiguous equal chunks per thread).

    Tiles sorted by cost (list length) are dealt round-robin to ``n_threads`` groups, which are
    then concatenated: every thread gets a similar mix of heavy and light tiles.
    """
    by_cost = np.argsort(-cost, kind="stable")
    return np.concatenate([by_cost[t::n_threads] for t in range(max(n_threads, 1))]).astype(
        np.int64)


class _Laps:
    """Adds the seconds since the previous lap to ``timings[name]`` (wall clock) and to
    ``timings[name + "_cpu"]`` (process CPU time, all threads); a no-op without a dict."""

    def __init__(self, timings: dict | None):
        self.timings = timings
        self.last = time.perf_counter()
        self.last_cpu = time.process_time()

    def __call__(self, name: str) -> None:
        if self.timings is None:
            return
        now, now_cpu = time.perf_counter(), time.process_time()
        self.timings[name] = self.timings.get(name, 0.0) + (now - self.last)
        key = name + "_cpu"
        self.timings[key] = self.timings.get(key, 0.0) + (now_cpu - self.last_cpu)
        self.last, self.last_cpu = now, now_cpu


def forward_numpy(means, log_scales, quats, logits, sh, deg, cam, width, height, bg,
                  timings: dict | None = None, exact_tiles: bool = True):
    """Render with the numba kernels. Returns ``(rgb, depth, alpha, ForwardState)``.

    Args:
        means [N,3], log_scales [N,3], quats [N,4], logits [N], sh [N,K,3]: float32 numpy.
        deg: SH degree. cam: [23] from :func:`camera_vector`. bg: [3] float32.
        timings: optional dict that receives per-stage seconds (for the benchmark).
        exact_tiles: skip the bounding-box tiles the ellipse misses (same output; False is the
            binning before that test, for measurements).
    """
    with _threads_for(means.shape[0], int(width) * int(height)):
        return _forward_numpy(means, log_scales, quats, logits, sh, deg, cam, width, height,
                              bg, timings, exact_tiles)


def _forward_numpy(means, log_scales, quats, logits, sh, deg, cam, width, height, bg, timings,
                   exact_tiles):
    lap = _Laps(timings)
    n = means.shape[0]
    W, H = int(width), int(height)
    tiles_x, tiles_y = (W + c.TILE - 1) // c.TILE, (H + c.TILE - 1) // c.TILE
    n_tiles = tiles_x * tiles_y
    packed_all = np.zeros((n, k.NPACK), np.float32)
    rect = np.zeros((n, 4), np.int32)
    if n:
        k.project_fwd(means, log_scales, quats, logits, sh, deg, cam, W, H, packed_all, rect)
    lap("project")
    visible = np.flatnonzero((rect[:, 2] > rect[:, 0]) & (rect[:, 3] > rect[:, 1]))
    # front-to-back order: sort (depth, index) packed in uint64 keys; depth > NEAR > 0, so the
    # float32 bit pattern orders like the value. Equals a stable argsort, several times faster.
    keys = packed_all[visible, 9].view(np.uint32).astype(np.uint64) << np.uint64(32)
    keys |= visible.astype(np.uint64)
    keys.sort()
    order = (keys & np.uint64(0xFFFFFFFF)).astype(np.int64)
    lap("sort")
    packed = k.gather_rows(packed_all, order) if len(order) else np.zeros((0, k.NPACK),
                                                                           np.float32)
    rect_sorted = k.gather_rows(rect, order) if len(order) else np.zeros((0, 4), np.int32)
    tile_off, g_off, pair_dst, records = k.bin_tiles(rect_sorted, packed, tiles_x, n_tiles, H,
                                                      bool(exact_tiles))
    tile_order = _balanced_tile_order(np.diff(tile_off), numba.get_num_threads())
    lap("bin")
    rgb = np.zeros((H, W, 3), np.float32)
    depth = np.zeros((H, W), np.float32)
    alpha = np.zeros((H, W), np.float32)
    t_final = np.ones((H, W), np.float32)
    last = np.zeros((H, W), np.int32)
    k.blend_fwd(records, tile_off, tile_order, W, H, tiles_x, bg,
                rgb, depth, alpha, t_final, last)
    lap("blend")
    if timings is not None:
        timings["pairs"] = int(tile_off[-1])
        timings["visible"] = int(len(order))
    state = ForwardState((means, log_scales, quats, logits, sh), deg, cam, W, H, tiles_x, bg,
                         rect, order, records, tile_off, tile_order, g_off,
                         pair_dst, depth, alpha, t_final, last)
    return rgb, depth, alpha, state


def backward_numpy(state: ForwardState, g_rgb, g_depth, g_alpha, timings: dict | None = None):
    """Gradients w.r.t. (means, log_scales, quats, logits, sh): float32 numpy arrays.

    The per-Gaussian math is float64; results are stored as float32 (the forward is float32).

    Args:
        g_rgb [H,W,3], g_depth [H,W], g_alpha [H,W]: float32 upstream gradients.
    """
    with _threads_for(state.inputs[0].shape[0], state.width * state.height):
        return _backward_numpy(state, g_rgb, g_depth, g_alpha, timings)


def _backward_numpy(state, g_rgb, g_depth, g_alpha, timings):
    lap = _Laps(timings)
    s = state
    means, log_scales, quats, logits, sh = s.inputs
    n = means.shape[0]
    pair_grad = np.zeros((len(s.records), k.NPAR), np.float32)  # unvisited pairs: 0
    k.blend_bwd(s.records, s.tile_off, s.pair_dst, s.tile_order, s.width, s.height,
                s.tiles_x, s.bg, s.depth, s.alpha, s.t_final, s.last, g_rgb, g_depth,
                g_alpha, pair_grad)
    lap("blend_bwd")
    dt = np.float32
    g_means = np.zeros((n, 3), dt)
    g_ls = np.zeros((n, 3), dt)
    g_q = np.zeros((n, 4), dt)
    g_lg = np.zeros(n, dt)
    g_sh = np.zeros(sh.shape, dt)
    if len(s.order):
        g2d = np.zeros((n, k.NPAR), np.float64)
        k.reduce_pairs(pair_grad, s.g_off, s.order, g2d)
        visible = np.zeros(n, np.bool_)
        visible[s.order] = True
        lap("reduce")
        k.project_bwd(means, log_scales, quats, logits, sh, s.deg, s.cam, visible, g2d,
                      g_means, g_ls, g_q, g_lg, g_sh)
    lap("project_bwd")
    return g_means, g_ls, g_q, g_lg, g_sh


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, log_scales, quats_wxyz, opacity_logits, sh, deg, cam, width,
                height, bg, exact_tiles):
        arrs = [_np32(t) for t in (means, log_scales, quats_wxyz, opacity_logits, sh)]
        rgb, depth, alpha, state = forward_numpy(*arrs, deg, cam, width, height, bg,
                                                 exact_tiles=exact_tiles)
        ctx.state = state
        ctx.dtypes = [t.dtype for t in (means, log_scales, quats_wxyz, opacity_logits, sh)]
        ctx.device = means.device
        return torch.from_numpy(rgb), torch.from_numpy(depth), torch.from_numpy(alpha)

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_alpha):
        s = ctx.state
        H, W = s.height, s.width

        def as_np(g, shape):
            if g is None:
                return np.zeros(shape, np.float32)
            return _np32(g.reshape(shape))

        grads = backward_numpy(s, as_np(g_rgb, (H, W, 3)), as_np(g_depth, (H, W)),
                               as_np(g_alpha, (H, W)))
        out = [torch.from_numpy(g).to(dtype=dt, device=ctx.device)
               for g, dt in zip(grads, ctx.dtypes)]
        return (*out, None, None, None, None, None, None)


def rasterize_cpu(means, log_scales, quats_wxyz, opacity_logits, sh, world_from_cam,
                  fx, fy, cx, cy, width, height, sh_degree=None, background=(0.0, 0.0, 0.0),
                  exact_tiles: bool = True):
    """Numba CPU rasterizer; same arguments and output as :func:`~freescale_core.raster.rasterize`.

    Returns:
        :class:`~freescale_core.raster.RenderOutput`, float32 on the device of ``means``.
    """
    from . import RenderOutput

    _, deg = c.check_inputs(means, log_scales, quats_wxyz, opacity_logits, sh, sh_degree)
    width, height = int(width), int(height)
    cam = camera_vector(world_from_cam, fx, fy, cx, cy, width, height)
    bg = np.asarray(c.background_tuple(background), np.float32)
    rgb, depth, alpha = _RasterizeCPU.apply(means, log_scales, quats_wxyz, opacity_logits, sh,
                                            deg, cam, width, height, bg, exact_tiles)
    dev = means.device
    return RenderOutput(rgb.to(dev), depth.to(dev), alpha.to(dev))
