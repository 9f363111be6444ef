"""Benchmark of the CPU Gaussian rasterizer (freescale_core.raster, backend "cpu").

Forward and forward+backward milliseconds for square images of 128/256/512 px and 10k/100k/300k
Gaussians, median of a few runs after warm-up, and the peak RSS of the process.

    python benchmarks/rasterizer.py              # full table
    python benchmarks/rasterizer.py --quick      # small rows only (smoke test)
    python benchmarks/rasterizer.py --json       # one JSON object per row
    python benchmarks/rasterizer.py --breakdown  # time per stage + arithmetic-limit estimate
    python benchmarks/rasterizer.py --torch-blend  # also time a vectorised-torch blend

Scene (mirrors a trained 3DGS scene seen from one of its cameras): camera at the origin looking
down +z with a 70 degree horizontal FOV; means uniform in the view frustum (plus a 10 % margin)
at depths 2..8; 3-sigma footprints of a few pixels at 256 px (per-axis sigma = exp(N(ln 1, 0.5))
px, anisotropic by exp(U(-0.5, 0.5)) per axis); random rotations; opacity logits N(0, 2)
(many faint, some opaque Gaussians, as after training); SH degree 3 with small higher-order
coefficients. The same world scene is rendered at every resolution, so footprints scale with it.
"""

from __future__ import annotations

import os
import sys

# benchmarks/select.py (another benchmark) would shadow the stdlib ``select`` module that
# torch imports; drop this script's folder from the import path before anything else.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from freescale_core.raster import _common as C  # noqa: E402
from freescale_core.raster import cpu, kernels, rasterize  # noqa: E402

HFOV_DEG = 70.0


def intrinsics(size: int):
    f = 0.5 * size / np.tan(np.radians(HFOV_DEG) / 2)
    return f, f, size / 2.0, size / 2.0


def make_scene(n: int, seed: int = 0, sh_degree: int = 3):
    """Random scene in front of an identity camera; returns float32 torch tensors."""
    rng = np.random.default_rng(seed)
    fx, _, _, _ = intrinsics(256)
    tan = np.tan(np.radians(HFOV_DEG) / 2) * 1.1
    z = rng.uniform(2.0, 8.0, n)
    x = rng.uniform(-tan, tan, n) * z
    y = rng.uniform(-tan, tan, n) * z
    means = np.stack([x, y, z], 1)
    sigma_px = np.exp(rng.normal(0.0, 0.5, n))  # at 256 px
    log_scales = np.log(sigma_px * z / fx)[:, None] + rng.uniform(-0.5, 0.5, (n, 3))
    quats = rng.normal(size=(n, 4))
    logits = rng.normal(0.0, 2.0, n)
    k = (sh_degree + 1) ** 2
    sh = rng.normal(0.0, 0.15, (n, k, 3))
    sh[:, 0] = rng.normal(0.0, 1.0, (n, 3))
    return [torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))
            for a in (means, log_scales, quats, logits, sh)]


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def time_row(params, size: int, repeats: int):
    """Median forward and forward+backward ms of the CPU backend."""
    fx, fy, cx, cy = intrinsics(size)
    pose = np.eye(4)

    def fwd():
        with torch.no_grad():
            return rasterize(*params, pose, fx, fy, cx, cy, size, size, backend="cpu")

    ps = [p.clone().requires_grad_(True) for p in params]
    g = torch.Generator().manual_seed(1)
    # upstream gradients given directly (no loss ops: only the rasterizer is timed)
    g_out = [torch.randn(size, size, 3, generator=g), torch.randn(size, size, generator=g) * 0.1,
             torch.randn(size, size, generator=g)]

    def fwd_bwd():
        for p in ps:
            p.grad = None
        out = rasterize(*ps, pose, fx, fy, cx, cy, size, size, backend="cpu")
        torch.autograd.backward([out.rgb, out.depth, out.alpha], g_out)

    fwd()
    fwd_bwd()  # warm-up (also compiles on a cold numba cache)
    tf, tfb = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fwd()
        tf.append(time.perf_counter() - t0)
    for _ in range(repeats):
        t0 = time.perf_counter()
        fwd_bwd()
        tfb.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(tf), 1e3 * statistics.median(tfb)


# --------------------------------------------------------------------------- breakdown
def count_evaluations(state) -> tuple[int, int]:
    """Gaussian-pixel evaluations of the forward blend: (lane evaluations, in-ellipse pairs)."""
    return _count_evals(state.records, state.tile_off, state.last, state.width, state.height,
                        state.tiles_x)


def _count_evals_py(records, tile_off, last, W, H, tiles_x):
    n_tiles = len(tile_off) - 1
    lanes = 0
    for t in range(n_tiles):
        ty, tx = divmod(t, tiles_x)
        x0, y0 = tx * C.TILE, ty * C.TILE
        y_end = min(y0 + C.TILE, H)
        block = last[y0:y_end, x0:min(x0 + C.TILE, W)]
        n_used = int(block.max()) + 1 if block.size else 0
        for j in range(tile_off[t], min(tile_off[t + 1], tile_off[t] + n_used)):
            v, ey = records[j, 1], records[j, 11]
            lo = max(int(np.ceil(v - ey - 0.5)), y0)
            hi = min(int(np.floor(v + ey - 0.5)) + 1, y_end)
            lanes += max(hi - lo, 0) * C.TILE
    return lanes, 0


def _count_evals(*args):
    from numba import njit

    return njit(cache=False)(_count_evals_py)(*args)


def fma_gflops(seconds: float = 0.5) -> float:
    """Measured float32 FLOP/s of a vectorised numba FMA loop on all threads (GFLOP/s)."""
    from numba import njit, prange

    @njit(parallel=True, fastmath=True)
    def kernel(a, reps):
        n = a.shape[0]
        out = np.zeros(n, np.float32)
        for i in prange(n // 16):
            acc = np.zeros(16, np.float32)
            x = a[i * 16:i * 16 + 16].copy()
            for _ in range(reps):
                for k in range(16):
                    acc[k] = acc[k] * np.float32(0.999) + x[k]
            out[i * 16:i * 16 + 16] = acc
        return out

    a = np.random.default_rng(0).random(16 * 4096).astype(np.float32)
    kernel(a, 10)
    reps = 2000
    t0 = time.perf_counter()
    kernel(a, reps)
    dt = time.perf_counter() - t0
    return 2.0 * a.shape[0] * reps / dt / 1e9


FLOPS_PER_LANE_EVAL = 45  # power 9, exp ~20, alpha/threshold/compositing ~16


def breakdown(params, size: int, repeats: int) -> dict:
    fx, fy, cx, cy = intrinsics(size)
    arrs = [p.numpy() for p in params]
    deg = int(round(np.sqrt(arrs[4].shape[1]))) - 1
    cam = cpu.camera_vector(np.eye(4), fx, fy, cx, cy, size, size)
    bg = np.zeros(3, np.float32)
    g = np.random.default_rng(1)
    g_rgb = g.standard_normal((size, size, 3)).astype(np.float32)
    g_d = g.standard_normal((size, size)).astype(np.float32)
    g_a = np.ones((size, size), np.float32)
    cpu.forward_numpy(*arrs, deg, cam, size, size, bg)  # warm-up
    rows = []
    for _ in range(repeats):
        tm: dict = {}
        _, _, _, state = cpu.forward_numpy(*arrs, deg, cam, size, size, bg, timings=tm)
        cpu.backward_numpy(state, g_rgb, g_d, g_a, timings=tm)
        rows.append(tm)
    med = {k: 1e3 * statistics.median(r[k] for r in rows)
           for k in ("project", "sort_bin", "blend", "blend_bwd", "project_bwd")}
    lanes, _ = count_evaluations(state)
    gflops = fma_gflops()
    achieved = lanes * FLOPS_PER_LANE_EVAL / (med["blend"] / 1e3) / 1e9
    return {"width": size, "height": size, "n_gaussians": len(arrs[0]),
            "visible": rows[-1]["visible"], "pairs": rows[-1]["pairs"],
            **{k + "_ms": round(v, 2) for k, v in med.items()},
            "blend_lane_evals": lanes, "blend_gflops_est": round(achieved, 1),
            "fma_peak_gflops": round(gflops, 1),
            "blend_fraction_of_peak": round(achieved / gflops, 3)}


# --------------------------------------------------------------------------- torch blend
def torch_blend_ms(params, size: int, repeats: int = 2) -> float:
    """Forward blend written with vectorised torch ops per tile (same binning), for comparison."""
    fx, fy, cx, cy = intrinsics(size)
    arrs = [p.numpy() for p in params]
    cam = cpu.camera_vector(np.eye(4), fx, fy, cx, cy, size, size)
    _, _, _, s = cpu.forward_numpy(*arrs, 3, cam, size, size, np.zeros(3, np.float32))
    P = torch.from_numpy(s.records)
    ys, xs = torch.meshgrid(torch.arange(C.TILE) + 0.5, torch.arange(C.TILE) + 0.5,
                            indexing="ij")
    xs, ys = xs.reshape(1, -1), ys.reshape(1, -1)

    def run():
        img = torch.zeros(s.height, s.width, 3)
        for t in range(len(s.tile_off) - 1):
            a, b = int(s.tile_off[t]), int(s.tile_off[t + 1])
            if a == b:
                continue
            ty, tx = divmod(t, s.tiles_x)
            g = P[a:b]
            dx = xs + tx * C.TILE - g[:, 0:1]
            dy = ys + ty * C.TILE - g[:, 1:2]
            power = 0.5 * (g[:, 2:3] * dx * dx + g[:, 4:5] * dy * dy) + g[:, 3:4] * dx * dy
            raw = g[:, 5:6] * torch.exp(-power)
            alpha = torch.where((power <= C.POWER_MAX) & (raw >= C.ALPHA_MIN),
                                raw.clamp(max=C.ALPHA_MAX), torch.zeros_like(raw))
            t_after = torch.cumprod(1 - alpha, 0)
            alpha = torch.where(t_after >= C.T_MIN, alpha, torch.zeros_like(alpha))
            t_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha[:-1]]), 0)
            rgb = (alpha * t_before).T @ g[:, 6:9]
            h, w = min(C.TILE, s.height - ty * C.TILE), min(C.TILE, s.width - tx * C.TILE)
            img[ty * C.TILE:ty * C.TILE + h, tx * C.TILE:tx * C.TILE + w] = \
                rgb.reshape(C.TILE, C.TILE, 3)[:h, :w]
        return img

    run()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only 128 px with 10k Gaussians")
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--breakdown", action="store_true", help="time per stage instead")
    ap.add_argument("--torch-blend", action="store_true",
                    help="also time a vectorised-torch forward blend")
    ap.add_argument("--sizes", type=int, nargs="*", default=None)
    ap.add_argument("--counts", type=int, nargs="*", default=None)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    sizes = args.sizes or ([128] if args.quick else [128, 256, 512])
    counts = args.counts or ([10_000] if args.quick else [10_000, 100_000, 300_000])
    print(f"# torch threads {torch.get_num_threads()}, numba threads "
          f"{__import__('numba').get_num_threads()}", file=sys.stderr)
    if not args.json:
        if args.breakdown:
            print(f"{'size':>5} {'N':>7} {'visible':>7} {'pairs':>8} {'proj':>6} {'sort':>6} "
                  f"{'blend':>6} {'bl_bwd':>6} {'pr_bwd':>6} {'Mlanes':>7} {'GF/s':>6} "
                  f"{'peak':>6}")
        else:
            print(f"{'size':>5} {'N':>7} {'fwd ms':>8} {'fwd+bwd ms':>11} {'peak MB':>8}"
                  + (f" {'torch blend ms':>15}" if args.torch_blend else ""))
    for n in counts:
        params = make_scene(n)
        for size in sizes:
            if args.breakdown:
                row = breakdown(params, size, args.repeats)
                row["peak_mb"] = round(peak_rss_mb(), 1)
                if args.json:
                    print(json.dumps(row), flush=True)
                else:
                    print(f"{size:>5} {n:>7} {row['visible']:>7} {row['pairs']:>8} "
                          f"{row['project_ms']:>6.1f} {row['sort_bin_ms']:>6.1f} "
                          f"{row['blend_ms']:>6.1f} {row['blend_bwd_ms']:>6.1f} "
                          f"{row['project_bwd_ms']:>6.1f} {row['blend_lane_evals'] / 1e6:>7.1f} "
                          f"{row['blend_gflops_est']:>6.1f} {row['fma_peak_gflops']:>6.1f}",
                          flush=True)
                continue
            f_ms, fb_ms = time_row(params, size, args.repeats)
            row = {"width": size, "height": size, "n_gaussians": n,
                   "forward_ms": round(f_ms, 2), "forward_backward_ms": round(fb_ms, 2),
                   "peak_mb": round(peak_rss_mb(), 1)}
            if args.torch_blend:
                row["torch_blend_ms"] = round(torch_blend_ms(params, size), 1)
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                print(f"{size:>5} {n:>7} {f_ms:>8.1f} {fb_ms:>11.1f} {row['peak_mb']:>8.1f}"
                      + (f" {row['torch_blend_ms']:>15.1f}" if args.torch_blend else ""),
                      flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
