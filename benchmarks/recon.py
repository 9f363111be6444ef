"""Benchmark of the reconstruction stage (METHOD.md stage 1) on real and sample scenes.

Trains on the paper's OOD split (first 70% of frames in capture order) and evaluates PSNR /
SSIM on the held-out 30% at the training resolution. Prints a table; ``--json`` prints one
JSON object per row instead.

    .venv/bin/python benchmarks/recon.py                       # buddha, strecha, sample scene
    .venv/bin/python benchmarks/recon.py /path/to/scene --preset cpu --json
    .venv/bin/python benchmarks/recon.py sample --max-minutes 10
    .venv/bin/python benchmarks/recon.py sample --split every8 --max-minutes 10 --eval-every 500

``--eval-every N`` also evaluates test PSNR every N training steps (the training clock and the
time budget are paused meanwhile; the evaluation seconds are reported) and prints the training
minutes at which test PSNR first reached ``--target-db`` (28). Those minutes are an upper bound
at the resolution of N steps.

Scene arguments: a folder (COLMAP layout), a shared dataset name, or ``sample`` (the embedded
sample scene, written to a temporary folder; its images are exact ground-truth renders).
"""

from __future__ import annotations

import sys
from pathlib import Path


import argparse
import json
import os
import tempfile
import time

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from freescale_core.recon.trainer import evaluate, reconstruct
from freescale_core.scene.scene import Scene
from schemas.pipeline import PipelineConfig
from schemas.recon import ReconConfig

DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))


def load(d: Path) -> Scene:
    """The project's own reader (undistortion and input pre-filter included)."""
    from freescale_core.scene.io import load_scene

    return load_scene(d)


def resolve(arg: str, tmp: Path) -> Path | None:
    if arg == "sample":
        try:
            from freescale_core.scene.sample import write_sample_scene
        except ImportError:
            print("# sample scene module not available; skipped", file=sys.stderr)
            return None
        out = tmp / "sample"
        if not out.exists():
            write_sample_scene(out)
        return out
    p = Path(arg)
    if not p.is_dir():
        p = DATASETS / arg
    if not (p / "sparse" / "0").is_dir():
        print(f"# {arg}: no COLMAP model found ({p}); skipped", file=sys.stderr)
        return None
    return p


def sample_coverage(scene_dir: Path, scene: Scene, gaussians, train, test, scale: float,
                    bg) -> dict:
    """Sample scene only: how much of each test view the training views saw, from the oracle.

    A test pixel is *covered* if its true surface point (oracle depth) is seen, unoccluded
    (oracle depth agrees within 2%), by at least one training view, or if it is sky. PSNR on
    covered pixels separates reconstruction error from extrapolation into unseen space.
    """
    from freescale_core.raster import render_gaussians
    from freescale_core.scene.sample import SampleWorld

    world = SampleWorld.load(scene_dir)
    tr = scene.cameras.subset(train).scaled(scale)
    te = scene.cameras.subset(test).scaled(scale)
    tr_depth = [world.render(tr.world_from_cam[i], tr.fx[i], tr.fy[i], tr.cx[i], tr.cy[i],
                             int(tr.width[i]), int(tr.height[i]))[1] for i in range(len(tr))]
    cov, ps = [], []
    for j in range(len(te)):
        W, H = int(te.width[j]), int(te.height[j])
        gt, d = world.render(te.world_from_cam[j], te.fx[j], te.fy[j], te.cx[j], te.cy[j], W, H)
        ys, xs = np.mgrid[0:H, 0:W] + 0.5
        xc = np.stack([(xs - te.cx[j]) / te.fx[j] * d, (ys - te.cy[j]) / te.fy[j] * d, d], -1)
        Xw = xc.reshape(-1, 3) @ te.world_from_cam[j][:3, :3].T + te.world_from_cam[j][:3, 3]
        seen = (d.reshape(-1) <= 0)  # sky counts as covered
        for i in range(len(tr)):
            uv, z = tr.subset([i]).project(Xw)
            u, v, z = uv[0, :, 0], uv[0, :, 1], z[0]
            ok = (z > 1e-3) & (u >= 0) & (u < tr.width[i]) & (v >= 0) & (v < tr.height[i])
            ui = np.clip(u.astype(int), 0, tr.width[i] - 1)
            vi = np.clip(v.astype(int), 0, tr.height[i] - 1)
            dt = tr_depth[i][vi, ui]
            seen |= ok & (dt > 0) & (np.abs(dt - z) <= 0.02 * z)
        mask = seen.reshape(H, W)
        rgb, _, _ = render_gaussians(gaussians, te.world_from_cam[j], te.fx[j], te.fy[j],
                                     te.cx[j], te.cy[j], W, H, background=bg)
        err = ((rgb.astype(np.float64) - gt / 255.0) ** 2)[mask]
        cov.append(float(mask.mean()))
        ps.append(float(-10 * np.log10(max(err.mean(), 1e-12))) if err.size else float("nan"))
    return {"test_covered_fraction": cov, "test_psnr_covered": ps,
            "test_covered_mean": float(np.mean(cov)),
            "test_psnr_covered_mean": float(np.nanmean(ps))}


def first_reaching(curve: list[dict], target_db: float) -> dict | None:
    """The first checkpoint of ``curve`` whose test PSNR is at least ``target_db`` (or None)."""
    return next((c for c in curve if c["test_psnr"] >= target_db), None)


def run(scene_dir: Path, cfg: ReconConfig, split: str, seed: int, verbose: bool,
        save_dir: Path | None = None, eval_every: int = 0, target_db: float = 28.0) -> dict:
    scene = load(scene_dir)
    train, test = scene.split(split)
    load0 = os.getloadavg()[0]
    curve: list[dict] = []
    cpu0 = time.process_time()
    cpu_ck = [0.0]  # process CPU seconds spent in checkpoints so far

    def checkpoint(step, g, info):
        c, t = time.process_time(), time.perf_counter()
        ev = evaluate(g, scene, test, scale=info["train_scale"], background=cfg.background,
                      backend=cfg.raster_backend)
        curve.append({"step": step, "train_minutes": info["train_seconds"] / 60.0,
                      "train_cpu_minutes": (c - cpu0 - cpu_ck[0]) / 60.0,
                      "test_psnr": ev["psnr_mean"], "test_ssim": ev["ssim_mean"],
                      "n_gaussians": len(g), "sh_degree": info["sh_degree"],
                      "eval_seconds": time.perf_counter() - t,
                      "load_avg": os.getloadavg()[0]})
        cpu_ck[0] += time.process_time() - c
        if verbose:
            print(f"#   {scene.scene_id} step {step}: {curve[-1]['train_minutes']:.2f} train min, "
                  f"test PSNR {ev['psnr_mean']:.2f} dB", file=sys.stderr, flush=True)

    def progress(step, info):
        if verbose and step % 200 == 0:
            print(f"#   {scene.scene_id} step {step}: loss_ema {info['loss_ema']:.4f} "
                  f"n {info['n_gaussians']} {info['phase']} sh {info['sh_degree']}",
                  file=sys.stderr, flush=True)

    res = reconstruct(scene, cfg, seed=seed, train_idx=train, progress=progress,
                      checkpoint_every=eval_every, on_checkpoint=checkpoint)
    cpu_train = time.process_time() - cpu0 - cpu_ck[0]
    st = res.stats
    if save_dir is not None:
        from freescale_core.scene.ply import write_ply

        out = save_dir / scene.scene_id
        out.mkdir(parents=True, exist_ok=True)
        write_ply(out / "gaussians.ply", res.gaussians)
        (out / "recon_stats.json").write_text(json.dumps(st, indent=1))
    t = time.perf_counter()
    ev = evaluate(res.gaussians, scene, test, scale=st["train_scale"], background=cfg.background,
                  backend=cfg.raster_backend)
    extra = {}
    if eval_every:
        if curve and curve[-1]["step"] == st["iterations"]:
            curve.pop()  # the last checkpoint was the final model: keep its final evaluation
        curve.append({"step": st["iterations"], "train_minutes": st["recon_seconds"] / 60.0,
                      "train_cpu_minutes": cpu_train / 60.0, "test_psnr": ev["psnr_mean"],
                      "test_ssim": ev["ssim_mean"], "n_gaussians": st["n_gaussians"],
                      "sh_degree": st["sh_degree"], "eval_seconds": time.perf_counter() - t,
                      "load_avg": os.getloadavg()[0], "final": True})
        hit = first_reaching(curve, target_db)
        extra = {"eval_every": eval_every, "target_db": target_db, "test_psnr_curve": curve,
                 "checkpoint_seconds": st["checkpoint_seconds"],
                 "minutes_to_target": None if hit is None else hit["train_minutes"],
                 "cpu_minutes_to_target": None if hit is None else hit["train_cpu_minutes"],
                 "step_to_target": None if hit is None else hit["step"]}
    if (scene_dir / "scene.json").is_file():
        extra |= sample_coverage(scene_dir, scene, res.gaussians, train, test, st["train_scale"],
                                cfg.background)
    return {
        **extra,
        "scene": scene.scene_id, "split": split,
        "n_train": len(train), "n_test": len(test),
        "n_gaussians": st["n_gaussians"], "n_gaussians_budget": st["n_gaussians_budget"],
        "iterations": st["iterations"], "width": st["train_resolution"][0],
        "height": st["train_resolution"][1], "minutes": st["recon_seconds"] / 60.0,
        "recon_seconds": st["recon_seconds"], "cpu_minutes": cpu_train / 60.0,
        "recon_train_psnr": st["recon_train_psnr"],
        "recon_test_psnr": ev["psnr_mean"], "recon_test_ssim": ev["ssim_mean"],
        "test_psnr_per_view": ev["psnr"], "eval_seconds": time.perf_counter() - t,
        "iterations_per_second": st["iterations_per_second"], "sh_degree": st["sh_degree"],
        "reasons": st["reasons"], "load_avg_start": load0, "load_avg_end": os.getloadavg()[0],
        "threads": st["threads"], "seed": seed,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenes", nargs="*", default=["buddha", "strecha_fountain-P11", "sample"])
    ap.add_argument("--preset", default="cpu", help="ReconConfig preset: paper, cpu, fast")
    ap.add_argument("--split", default="ood", choices=["ood", "every8"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-minutes", type=float, default=None,
                    help="wall-clock budget per scene (annealing starts when reached)")
    ap.add_argument("--max-iterations", type=int, default=None)
    ap.add_argument("--max-long-side", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--json", action="store_true", help="one JSON object per row")
    ap.add_argument("--save-dir", type=Path, default=None,
                    help="write <scene>/gaussians.ply and recon_stats.json here")
    ap.add_argument("--eval-every", type=int, default=0, metavar="N",
                    help="also evaluate test PSNR every N steps (clock paused while it runs) "
                    "and report the training minutes at which it first reached --target-db")
    ap.add_argument("--target-db", type=float, default=28.0)
    ap.add_argument("-v", "--verbose", action="store_true")
    a = ap.parse_args(argv)

    upd = {}
    if a.max_minutes is not None:
        upd["max_seconds"] = 60.0 * a.max_minutes
    if a.max_iterations is not None:
        upd["max_iterations"] = a.max_iterations
    if a.max_long_side is not None:
        upd["max_long_side"] = a.max_long_side
    if a.threads is not None:
        upd["threads"] = a.threads
    cfg = PipelineConfig.from_preset(a.preset).recon.model_copy(update=upd)
    cfg = ReconConfig.model_validate(cfg.model_dump())

    rows = []
    with tempfile.TemporaryDirectory(prefix="freescale_bench_recon_") as tmp:
        for s in a.scenes:
            d = resolve(s, Path(tmp))
            if d is None:
                continue
            row = run(d, cfg, a.split, a.seed, a.verbose, a.save_dir, a.eval_every,
                      a.target_db)
            row["preset"] = a.preset
            rows.append(row)
            if a.json:
                print(json.dumps(row), flush=True)
    if not a.json:
        print(f"# preset {a.preset}, split {a.split}, seed {a.seed}, {os.cpu_count()} cores")
        hdr = (f"{'scene':<22} {'n_gauss':>8} {'iters':>6} {'resolution':>10} {'min':>6} "
               f"{'cpu min':>7} {'train dB':>8} {'test dB':>8} {'test SSIM':>9} {'it/s':>6} "
               f"{'load':>9}")
        print(hdr)
        for r in rows:
            print(f"{r['scene']:<22} {r['n_gaussians']:>8} {r['iterations']:>6} "
                  f"{r['width']:>4}x{r['height']:<5} {r['minutes']:>6.2f} "
                  f"{r['cpu_minutes']:>7.2f} {r['recon_train_psnr']:>8.2f} "
                  f"{r['recon_test_psnr']:>8.2f} "
                  f"{r['recon_test_ssim']:>9.3f} {r['iterations_per_second']:>6.2f} "
                  f"{r['load_avg_start']:>4.1f}/{r['load_avg_end']:<4.1f}")
        for r in rows:
            if "test_covered_mean" in r:
                print(f"# {r['scene']}: oracle coverage of test views by training views "
                      f"{r['test_covered_mean']:.1%} (per view "
                      f"{[round(c, 2) for c in r['test_covered_fraction']]}); test PSNR on "
                      f"covered pixels {r['test_psnr_covered_mean']:.2f} dB")
            print(f"# {r['scene']}: test PSNR per view "
                  f"{[round(p, 1) for p in r['test_psnr_per_view']]}")
        for r in rows:
            if "test_psnr_curve" not in r:
                continue
            print(f"# {r['scene']}: test PSNR every {r['eval_every']} steps (clock paused for "
                  f"{r['checkpoint_seconds']:.0f} s of evaluation):")
            print(f"#   {'step':>6} {'train min':>9} {'cpu min':>8} {'test dB':>8} "
                  f"{'test SSIM':>9} {'n_gauss':>8} {'load':>5}")
            for c in r["test_psnr_curve"]:
                print(f"#   {c['step']:>6} {c['train_minutes']:>9.2f} "
                      f"{c['train_cpu_minutes']:>8.2f} {c['test_psnr']:>8.2f} "
                      f"{c['test_ssim']:>9.3f} {c['n_gaussians']:>8} {c['load_avg']:>5.1f}"
                      + ("  (final)" if c.get("final") else ""))
            if r["minutes_to_target"] is None:
                print(f"# {r['scene']}: test PSNR never reached {r['target_db']:g} dB")
            else:
                print(f"# {r['scene']}: test PSNR first >= {r['target_db']:g} dB at step "
                      f"{r['step_to_target']}, {r['minutes_to_target']:.2f} training minutes "
                      f"({r['cpu_minutes_to_target']:.2f} process-CPU minutes)")
        for r in rows:
            print(f"# {r['scene']}: " + "; ".join(f"{k}: {v}" for k, v in r["reasons"].items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
