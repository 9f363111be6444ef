"""Benchmark of the CPU Gaussian rasterizer (freescale_core.raster, backend "cpu").

Forward and forward+backward milliseconds for square images of 128/256/512 px and 10k/100k/300k
Gaussians, median of a few runs after warm-up, and the peak RSS of the process.

    python -m benchmarks.rasterizer              # full table
    python -m benchmarks.rasterizer --quick      # small rows only (smoke test)
    python -m benchmarks.rasterizer --json       # one JSON object per row
    python -m benchmarks.rasterizer --breakdown  # time per stage + arithmetic-limit estimate
    python -m benchmarks.rasterizer --torch-blend  # also time a vectorised-torch blend
    python -m benchmarks.rasterizer --quick --trainer  # + trainer it/s on two real scenes
    python -m benchmarks.rasterizer --model DIR/gaussians.ply --scene dtu_scan24 --split every8
        # a trained model on its training views: per stage, exact tile test on vs off

``--model`` takes a reconstruction saved by ``python -m benchmarks.recon --save-dir`` (its
``recon_stats.json`` beside the PLY gives the training scale and SH degree) and renders the
first ``--views`` training views of ``--split``, forward and backward (random upstream
gradients), with the binning's exact tile test on and off (``exact_tiles``; the same images and
gradients, checked in the run), alternating the two per view and repeat, single numba thread;
it prints the median process-CPU ms per view of each stage and the ratio, measured in the same
run. Trained scenes have many large, tilted Gaussians, which the synthetic scene below lacks.

``--trainer`` (not in the default run: ~55 s on top of its ~10 s) runs the real trainer,
``freescale_core.recon.trainer.reconstruct`` with the ``cpu`` preset, for ``--trainer-steps`` steps on
each of buddha and strecha_fountain-P11 from ``../shared/datasets`` (``FREESCALE_DATASETS``),
read by the project's reader ``freescale_core.scene.io.load_scene``; a missing scene is skipped with
the reason. To time the size training spends its time at, the preset's schedule is compressed
into the capped run (:func:`trainer_config`): MCMC growth reaches the scene's Gaussian budget
and SH degree 3 is reached within the first half; iterations/s is measured over the second
half (setup, image loading and the final train-PSNR evaluation excluded).

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

import argparse
import json
import resource
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from freescale_core.raster import _common as C
from freescale_core.raster import cpu, rasterize

HFOV_DEG = 70.0
REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))
TRAINER_SCENES = ("buddha", "strecha_fountain-P11")


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


def time_row(params, size: int, repeats: int) -> dict:
    """Median forward and forward+backward wall ms (and process CPU ms) of the CPU backend."""
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
    res = {}
    for name, fn in (("forward", fwd), ("forward_backward", fwd_bwd)):
        wall, cpu_t = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            fn()
            wall.append(time.perf_counter() - t0)
            cpu_t.append(time.process_time() - c0)
        res[name + "_ms"] = round(1e3 * statistics.median(wall), 1)
        res[name + "_cpu_ms"] = round(1e3 * statistics.median(cpu_t), 1)
    return res


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
            lo, hi = int(records[j, 10]), int(records[j, 11])  # the pair's rows (bin_tiles)
            lanes += max(hi - lo, 0) * C.TILE
    return lanes, 0


def _count_evals(*args):
    from numba import njit

    return njit(cache=False)(_count_evals_py)(*args)


def fma_gflops() -> tuple[float, float]:
    """float32 GFLOP/s of a vectorised numba FMA loop on all numba threads: (per wall second,
    per CPU second). Each element of an L1-resident array gets a degree-8 polynomial (8
    dependent FMAs; the 16-lane vectors of neighbouring elements hide the FMA latency)."""
    from numba import njit, prange

    @njit(parallel=True, fastmath=True, cache=False)
    def kernel(x, y, reps):
        c = np.float32(0.5)
        for t in prange(x.shape[0]):
            for _ in range(reps):
                for k in range(x.shape[1]):
                    v = x[t, k]
                    p = c * v + c
                    p = p * v + c
                    p = p * v + c
                    p = p * v + c
                    p = p * v + c
                    p = p * v + c
                    p = p * v + c
                    p = p * v + c
                    y[t, k] += p
        return y

    nt = __import__("numba").get_num_threads()
    x = np.random.default_rng(0).random((nt, 2048)).astype(np.float32)
    y = np.zeros_like(x)
    kernel(x, y, 2)
    reps = 20_000
    t0, c0 = time.perf_counter(), time.process_time()
    kernel(x, y, reps)
    wall, cpu_t = time.perf_counter() - t0, time.process_time() - c0
    flops = 17.0 * x.size * reps  # 8 FMAs + 1 add per element
    return flops / wall / 1e9, flops / cpu_t / 1e9


FLOPS_PER_LANE_EVAL = 45  # power 9, exp ~20, alpha/threshold/compositing ~16


STAGES = ("project", "sort", "bin", "blend", "blend_bwd", "reduce", "project_bwd")


def breakdown(params, size: int, repeats: int) -> dict:
    """Median wall and CPU ms per stage, and the blend's distance from the FMA roofline."""
    fx, fy, cx, cy = intrinsics(size)
    arrs = [p.numpy() for p in params]
    deg = int(round(np.sqrt(arrs[4].shape[1]))) - 1
    cam = cpu.camera_vector(np.eye(4), fx, fy, cx, cy, size, size)
    bg = np.zeros(3, np.float32)
    g = np.random.default_rng(1)
    g_rgb = g.standard_normal((size, size, 3)).astype(np.float32)
    g_d = g.standard_normal((size, size)).astype(np.float32)
    g_a = np.ones((size, size), np.float32)
    _, _, _, state = cpu.forward_numpy(*arrs, deg, cam, size, size, bg)  # warm-up
    cpu.backward_numpy(state, g_rgb, g_d, g_a)
    rows = []
    for _ in range(repeats):
        tm: dict = {}
        _, _, _, state = cpu.forward_numpy(*arrs, deg, cam, size, size, bg, timings=tm)
        cpu.backward_numpy(state, g_rgb, g_d, g_a, timings=tm)
        rows.append(tm)
    med = {k: 1e3 * statistics.median(r.get(k, 0.0) for r in rows)
           for s_ in STAGES for k in (s_, s_ + "_cpu")}
    lanes, _ = count_evaluations(state)
    peak_wall, peak_cpu = fma_gflops()
    flops = lanes * FLOPS_PER_LANE_EVAL
    blend_wall = flops / (med["blend"] / 1e3) / 1e9
    blend_cpu = flops / (med["blend_cpu"] / 1e3) / 1e9
    return {"width": size, "height": size, "n_gaussians": len(arrs[0]),
            "visible": rows[-1]["visible"], "pairs": rows[-1]["pairs"],
            **{k + "_ms": round(v, 2) for k, v in med.items()},
            "blend_lane_evals": lanes,
            "blend_gflops_wall": round(blend_wall, 1), "fma_gflops_wall": round(peak_wall, 1),
            "blend_gflops_cpu": round(blend_cpu, 1), "fma_gflops_cpu": round(peak_cpu, 1),
            "blend_fraction_of_fma_cpu": round(blend_cpu / peak_cpu, 3)}


# --------------------------------------------------------------------------- trained model
def model_rows(ply: Path, scene_arg: str, split: str, n_views: int, repeats: int) -> list[dict]:
    """Median per-view CPU ms per stage of a trained model, exact tile test on and off."""
    import numba

    from freescale_core.scene.io import load_scene
    from freescale_core.scene.ply import read_ply

    scene_dir = Path(scene_arg) if Path(scene_arg).is_dir() else DATASETS / scene_arg
    if not scene_dir.is_dir():
        raise SystemExit(f"{scene_arg}: no such scene folder (looked in {DATASETS})")
    stats_path = ply.parent / "recon_stats.json"
    if not stats_path.is_file():
        raise SystemExit(f"{ply}: no recon_stats.json beside it (save with recon.py --save-dir)")
    stats = json.loads(stats_path.read_text())
    scene = load_scene(scene_dir)
    g = read_ply(ply, scene.scene_id)
    train, _ = scene.split(split)
    cams = scene.cameras.subset(np.asarray(train)[:n_views]).scaled(float(stats["train_scale"]))
    deg = int(stats["sh_degree"])
    arrs = [np.ascontiguousarray(a, np.float32)
            for a in (g.means, g.log_scales, g.quats_wxyz, g.opacity_logits, g.sh)]
    numba.set_num_threads(1)
    laps: dict[bool, list[dict]] = {True: [], False: []}
    rng = np.random.default_rng(0)
    for rep in range(repeats + 1):  # the first pass warms up (and compiles)
        for j in range(len(cams.fx)):
            W, H = int(cams.width[j]), int(cams.height[j])
            cam = cpu.camera_vector(cams.world_from_cam[j], cams.fx[j], cams.fy[j], cams.cx[j],
                                    cams.cy[j], W, H)
            g_rgb = rng.standard_normal((H, W, 3)).astype(np.float32)
            zero = np.zeros((H, W), np.float32)
            outs = {}
            for exact in ((True, False) if (rep + j) % 2 == 0 else (False, True)):
                tm: dict = {}
                rgb, _, _, state = cpu.forward_numpy(*arrs, deg, cam, W, H,
                                                     np.zeros(3, np.float32), timings=tm,
                                                     exact_tiles=exact)
                grads = cpu.backward_numpy(state, g_rgb, zero, zero, timings=tm)
                outs[exact] = (rgb, grads)
                if rep:
                    laps[exact].append(tm)
            (a, ga), (b, gb) = outs[True], outs[False]
            if not (np.array_equal(a, b) and all(np.array_equal(x, y) for x, y in zip(ga, gb))):
                raise SystemExit(f"{scene.scene_id} view {j}: exact tile test changed the output")
    rows = []
    for exact in (False, True):
        tms = laps[exact]
        row = {"scene": scene.scene_id, "split": split, "exact_tiles": exact,
               "n_gaussians": len(arrs[0]), "width": W, "height": H, "views": len(cams.fx),
               "repeats": repeats, "pairs": int(statistics.median(t["pairs"] for t in tms))}
        for s_ in STAGES:
            row[s_ + "_cpu_ms"] = round(1e3 * statistics.median(t.get(s_ + "_cpu", 0.0)
                                                                 for t in tms), 2)
        row["total_cpu_ms"] = round(1e3 * statistics.median(
            sum(t.get(s_ + "_cpu", 0.0) for s_ in STAGES) for t in tms), 2)
        rows.append(row)
    rows[1]["total_ratio"] = round(rows[1]["total_cpu_ms"] / rows[0]["total_cpu_ms"], 3)
    return rows


# --------------------------------------------------------------------------- torch blend
def torch_blend_ms(params, size: int, repeats: int = 2) -> float:
    """Forward blend as vectorised torch ops (same binning and records), for comparison.

    Tiles are batched (lists padded to the longest in the batch, batches capped at ~32M
    Gaussian-pixel elements); every list entry is evaluated at all 256 pixels of its tile and
    composited with cumprod, so early termination saves nothing. Returns median wall ms.
    """
    fx, fy, cx, cy = intrinsics(size)
    arrs = [p.numpy() for p in params]
    cam = cpu.camera_vector(np.eye(4), fx, fy, cx, cy, size, size)
    _, _, _, s = cpu.forward_numpy(*arrs, 3, cam, size, size, np.zeros(3, np.float32))
    rec = torch.from_numpy(s.records)
    off = s.tile_off
    n_tiles = len(off) - 1
    ys, xs = torch.meshgrid(torch.arange(C.TILE) + 0.5, torch.arange(C.TILE) + 0.5,
                            indexing="ij")
    xs, ys = xs.reshape(1, 1, -1), ys.reshape(1, 1, -1)
    lens = np.diff(off)

    def run():
        img = torch.zeros(s.tiles_x * C.TILE * 0 + n_tiles, C.TILE * C.TILE, 3)
        t = 0
        while t < n_tiles:
            t1 = t + 1
            while t1 < n_tiles and (t1 + 1 - t) * max(lens[t:t1 + 1].max(), 1) * 256 < 32e6:
                t1 += 1
            L = int(max(lens[t:t1].max(), 1))
            idx = torch.from_numpy(off[t:t1]).unsqueeze(1) + torch.arange(L).unsqueeze(0)
            valid = torch.arange(L).unsqueeze(0) < torch.from_numpy(lens[t:t1]).unsqueeze(1)
            g = rec[idx.clamp(max=max(len(rec) - 1, 0))]  # [B, L, 12]
            tid = torch.arange(t, t1)
            ox = ((tid % s.tiles_x) * C.TILE).float().reshape(-1, 1, 1)
            oy = ((tid // s.tiles_x) * C.TILE).float().reshape(-1, 1, 1)
            dx = xs + ox - g[..., 0:1]
            dy = ys + oy - g[..., 1:2]
            power = 0.5 * (g[..., 2:3] * dx * dx + g[..., 4:5] * dy * dy) + g[..., 3:4] * dx * dy
            raw = g[..., 5:6] * torch.exp(-power)
            keep = (power <= C.POWER_MAX) & (raw >= C.ALPHA_MIN) & valid.unsqueeze(-1)
            alpha = torch.where(keep, raw.clamp(max=C.ALPHA_MAX), torch.zeros_like(raw))
            t_after = torch.cumprod(1 - alpha, 1)
            alpha = torch.where(t_after >= C.T_MIN, alpha, torch.zeros_like(alpha))
            t_before = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]),
                                                1 - alpha[:, :-1]], 1), 1)
            img[t:t1] = torch.einsum("blp,blc->bpc", alpha * t_before, g[..., 6:9])
            t = t1
        return img

    run()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts)


# --------------------------------------------------------------------------- trainer
def trainer_config(steps: int, preset: str = "cpu"):
    """``preset`` capped at ``steps`` steps, its schedule compressed into them: MCMC growth
    (``mcmc_grow_steps`` densifications) from step steps/10 to steps/2, SH degree +1 every
    steps/8 (degree 3 by steps/2), no plateau stop. The second half then runs at the scene's
    full Gaussian budget and SH degree, as most of a full-length training does."""
    from schemas.pipeline import PipelineConfig
    from schemas.recon import ReconConfig

    cfg = PipelineConfig.from_preset(preset).recon
    start, half = max(1, steps // 10), max(2, steps // 2)
    every = max(1, (half - start) // max(cfg.mcmc_grow_steps, 1))
    upd = {"max_iterations": steps, "min_iterations": steps + 1, "densify_from": start,
           "densify_every": every, "densify_until": half,
           "sh_increase_every": max(1, steps // 8)}
    return ReconConfig.model_validate(cfg.model_copy(update=upd).model_dump())


def trainer_row(scene_dir: Path, steps: int, preset: str = "cpu", seed: int = 0,
                cfg=None) -> dict:
    """Train ``steps`` steps on all views of the scene at ``scene_dir``; iterations/s over the
    second half of the steps (progress timestamps every 10 steps) and over the whole call."""
    from freescale_core.scene.io import load_scene
    from freescale_core.recon.trainer import reconstruct

    cfg = cfg or trainer_config(steps, preset)
    t0 = time.perf_counter()
    scene = load_scene(scene_dir)
    t_load = time.perf_counter() - t0
    stamps: list[tuple[int, float, int, int]] = []

    def progress(step, info):
        if info["phase"] != "done":
            stamps.append((step, time.perf_counter(), info["n_gaussians"], info["sh_degree"]))

    load0 = os.getloadavg()[0]
    res = reconstruct(scene, cfg, seed=seed, progress=progress)
    st = res.stats
    half = [x for x in stamps if x[0] >= steps // 2]
    if len(half) >= 2:
        (s0, t_a, _, _), (s1, t_b, _, _) = half[0], half[-1]
        ips_timed, timed = (s1 - s0) / max(t_b - t_a, 1e-9), [s0, s1]
    else:  # too few steps for a second-half window
        ips_timed, timed = st["iterations_per_second"], [0, st["iterations"]]
    return {"kind": "trainer", "scene": scene.scene_id, "preset": preset,
            "width": st["train_resolution"][0], "height": st["train_resolution"][1],
            "n_views": len(scene), "n_gaussians": st["n_gaussians"],
            "n_gaussians_budget": st["n_gaussians_budget"], "sh_degree": st["sh_degree"],
            "steps": st["iterations"], "timed_steps": timed,
            "iterations_per_second": round(ips_timed, 2),
            "iterations_per_second_overall": round(st["iterations_per_second"], 2),
            "load_seconds": round(t_load, 2), "train_seconds": round(st["train_seconds"], 2),
            "threads": st["threads"], "load_avg_start": load0,
            "load_avg_end": os.getloadavg()[0]}


def trainer_rows(steps: int, preset: str = "cpu", scenes=TRAINER_SCENES,
                 datasets: Path = DATASETS):
    """Yield a row per available shared scene, or ``{"scene", "skipped": reason}``."""
    for name in scenes:
        d = Path(datasets) / name
        if not (d / "sparse" / "0").is_dir():
            yield {"kind": "trainer", "scene": name,
                   "skipped": f"shared scene not found: {d} (set FREESCALE_DATASETS)"}
            continue
        yield trainer_row(d, steps, preset)


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
    ap.add_argument("--trainer", action="store_true",
                    help="also time the trainer (cpu preset) on buddha and strecha_fountain-P11")
    ap.add_argument("--trainer-steps", type=int, default=300)
    ap.add_argument("--model", type=Path, default=None,
                    help="a trained gaussians.ply (recon.py --save-dir): exact tiles on vs off")
    ap.add_argument("--scene", default=None, help="with --model: scene folder or shared name")
    ap.add_argument("--split", default="every8", help="with --model: whose training views")
    ap.add_argument("--views", type=int, default=10, help="with --model: training views used")
    args = ap.parse_args(argv)
    if args.model is not None:
        if args.scene is None:
            ap.error("--model needs --scene")
        rows = model_rows(args.model, args.scene, args.split, args.views, args.repeats)
        if args.json:
            for row in rows:
                print(json.dumps(row), flush=True)
            return 0
        r = rows[0]
        print(f"# {r['scene']} {r['split']}: {r['n_gaussians']} Gaussians, {r['views']} training "
              f"views at {r['width']}x{r['height']}, median of {r['repeats']} repeats, CPU ms "
              "per view, one thread, on/off alternating")
        print(f"{'exact':>5} {'pairs':>8} " + " ".join(f"{s_:>11}" for s_ in STAGES)
              + f" {'total':>8} {'ratio':>6}")
        for r in rows:
            print(f"{str(r['exact_tiles']):>5} {r['pairs']:>8} "
                  + " ".join(f"{r[s_ + '_cpu_ms']:>11.2f}" for s_ in STAGES)
                  + f" {r['total_cpu_ms']:>8.2f} {r.get('total_ratio', 1.0):>6.3f}")
        return 0
    sizes = args.sizes or ([128] if args.quick else [128, 256, 512])
    counts = args.counts or ([10_000] if args.quick else [10_000, 100_000, 300_000])
    print(f"# torch threads {torch.get_num_threads()}, numba threads "
          f"{__import__('numba').get_num_threads()} (cap {cpu.THREADS_ENV}="
          f"{os.environ.get(cpu.THREADS_ENV, '-')}, OMP_WAIT_POLICY="
          f"{os.environ.get('OMP_WAIT_POLICY', '-')}), load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}", file=sys.stderr)
    if not args.json:
        if args.breakdown:
            print("# per stage: wall ms / process-CPU ms (all threads); Mlanes = 16-lane blend"
                  " evaluations; GF/s per CPU second vs a numba FMA loop")
            print(f"{'size':>5} {'N':>7} {'pairs':>8} "
                  + " ".join(f"{s_:>13}" for s_ in STAGES)
                  + f" {'Mlanes':>7} {'GF/s':>5} {'FMA':>5}")
        else:
            print(f"{'size':>5} {'N':>7} {'fwd ms':>8} {'fwd+bwd ms':>11} {'fwd cpu':>8} "
                  f"{'f+b cpu':>8} {'peak MB':>8}"
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
                    cells = " ".join(f"{row[s_ + '_ms']:>6.1f}/{row[s_ + '_cpu_ms']:<6.1f}"
                                     for s_ in STAGES)
                    print(f"{size:>5} {n:>7} {row['pairs']:>8} {cells} "
                          f"{row['blend_lane_evals'] / 1e6:>7.1f} {row['blend_gflops_cpu']:>5.1f} "
                          f"{row['fma_gflops_cpu']:>5.1f}", flush=True)
                continue
            t = time_row(params, size, args.repeats)
            row = {"width": size, "height": size, "n_gaussians": n, **t,
                   "peak_mb": round(peak_rss_mb(), 1)}
            if args.torch_blend:
                row["torch_blend_ms"] = round(torch_blend_ms(params, size), 1)
            if args.json:
                print(json.dumps(row), flush=True)
            else:
                print(f"{size:>5} {n:>7} {t['forward_ms']:>8.1f} {t['forward_backward_ms']:>11.1f} "
                      f"{t['forward_cpu_ms']:>8.1f} {t['forward_backward_cpu_ms']:>8.1f} "
                      f"{row['peak_mb']:>8.1f}"
                      + (f" {row['torch_blend_ms']:>15.1f}" if args.torch_blend else ""),
                      flush=True)
    if args.trainer:
        if not args.json:
            print(f"# trainer: cpu preset compressed into {args.trainer_steps} steps; it/s over "
                  "the second half (full budget, SH 3); overall = whole reconstruct() call")
            print(f"{'scene':<22} {'resolution':>10} {'views':>5} {'n_gauss':>8} {'steps':>5} "
                  f"{'it/s':>6} {'overall':>7} {'load avg':>9}")
        for row in trainer_rows(args.trainer_steps):
            if args.json:
                print(json.dumps(row), flush=True)
            elif "skipped" in row:
                print(f"{row['scene']:<22} skipped: {row['skipped']}", flush=True)
            else:
                print(f"{row['scene']:<22} {row['width']:>4}x{row['height']:<5} "
                      f"{row['n_views']:>5} {row['n_gaussians']:>8} {row['steps']:>5} "
                      f"{row['iterations_per_second']:>6.2f} "
                      f"{row['iterations_per_second_overall']:>7.2f} "
                      f"{row['load_avg_start']:>4.1f}/{row['load_avg_end']:<4.1f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
