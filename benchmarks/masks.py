"""Object masks on a turntable capture: held-out PSNR on the object with and without masks.

    .venv/bin/python -m benchmarks.masks                   # fast preset, seed 0
    .venv/bin/python -m benchmarks.masks --seeds 0,1,2 --iterations 600

Writes the procedural turntable capture (:mod:`freescale_core.scene.turntable`: an object on
a full circle of cameras, a background that changes in every image, exact masks), holds out
every 8th view, and trains the same reconstruction (same preset, seed and budget) three ways:

* ``masks, background``: masks read, pixels outside trained toward the background colour
  (``recon.masked_pixels=background``, the default);
* ``masks, ignore``: masks read, pixels outside left out of the loss;
* ``no masks``: the same folder read with ``ingest.masks=ignore`` (what the engine did before).

Every variant is scored on the held-out views' *object* pixels (their masks), at the
training resolution and background; one table row per variant and seed.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path


def run(n_views: int, width: int, height: int, seeds: list[int], iterations: int | None,
        split: str, workdir: Path) -> list[dict]:
    from freescale_core.recon.trainer import evaluate, reconstruct
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.turntable import write_turntable_scene
    from schemas.ingest import IngestConfig
    from schemas.recon import ReconConfig

    scene_dir = write_turntable_scene(workdir / "turntable", n_views, width, height, seed=0)
    masked = load_scene(scene_dir, cache_dir=workdir / "cache")
    plain = load_scene(scene_dir, cache_dir=workdir / "cache", cfg=IngestConfig(masks="ignore"))
    train_idx, test_idx = masked.split(split)
    rows = []
    for seed in seeds:
        for name, scene, mode in (("masks, background", masked, "background"),
                                  ("masks, ignore", masked, "ignore"),
                                  ("no masks", plain, "background")):
            cfg = ReconConfig.fast().model_copy(update={"masked_pixels": mode})
            if iterations:
                cfg = cfg.model_copy(update={"max_iterations": iterations})
            t = time.perf_counter()
            r = reconstruct(scene, cfg, seed=seed, train_idx=train_idx)
            ev = evaluate(r.gaussians, masked, test_idx, scale=r.stats["train_scale"],
                          background=cfg.background, backend=cfg.raster_backend)
            rows.append({"variant": name, "seed": seed, "iterations": r.stats["iterations"],
                         "n_gaussians": r.stats["n_gaussians"],
                         "train_psnr": r.stats["recon_train_psnr"],
                         "heldout_object_psnr": ev["psnr_mean"],
                         "heldout_object_ssim": ev["ssim_mean"],
                         "seconds": time.perf_counter() - t})
            print("  " + " | ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}"
                                    for k, v in rows[-1].items()), file=sys.stderr, flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--width", type=int, default=96)
    ap.add_argument("--height", type=int, default=72)
    ap.add_argument("--seeds", default="0")
    ap.add_argument("--iterations", type=int, default=None,
                    help="max_iterations (default: the fast preset's)")
    ap.add_argument("--split", default="every8", choices=["every8", "ood"])
    a = ap.parse_args(argv)
    seeds = [int(s) for s in a.seeds.split(",")]
    with tempfile.TemporaryDirectory(prefix="fs_masks_") as tmp:
        rows = run(a.views, a.width, a.height, seeds, a.iterations, a.split, Path(tmp))
    print(f"turntable {a.views} views {a.width}x{a.height}, split {a.split}, fast preset"
          + (f", {a.iterations} iterations" if a.iterations else "") + "\n")
    print("| variant | seed | iterations | Gaussians | train PSNR (masks: object; no masks: "
          "whole image) | held-out PSNR (object) | held-out SSIM (object) | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['variant']} | {r['seed']} | {r['iterations']} | {r['n_gaussians']} | "
              f"{r['train_psnr']:.2f} | {r['heldout_object_psnr']:.2f} | "
              f"{r['heldout_object_ssim']:.3f} | {r['seconds']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
