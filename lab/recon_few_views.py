"""Held-out PSNR of a saved reconstruction without the Gaussians few training views see.

For a model written by ``benchmarks/recon.py --save-dir DIR`` (``DIR/<scene>/gaussians.ply``
and ``recon_stats.json``), counts how many training views have each Gaussian's centre in front
of the camera and inside the image (``freescale_core.recon.bounds.views_seeing``), and prints
per held-out view the PSNR of the whole model, of the model without the Gaussians exactly one
view sees, and without those no view sees (docs/RECON.md, stop 25).

    FREESCALE_DATASETS=../shared/datasets .venv/bin/python -m lab.recon_few_views \\
        strecha_fountain-P11 DIR --split ood
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from benchmarks.recon import load, resolve
from freescale_core.recon.bounds import views_seeing
from freescale_core.recon.trainer import evaluate
from freescale_core.scene.ply import read_ply


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("save_dir", type=Path)
    ap.add_argument("--split", default="ood")
    a = ap.parse_args(argv)
    d = resolve(a.scene, Path("/nonexistent"))
    if d is None:
        return 1
    scene = load(d)
    train, test = scene.split(a.split)
    out = a.save_dir / scene.scene_id
    g = read_ply(out / "gaussians.ply", scene.scene_id)
    stats = json.loads((out / "recon_stats.json").read_text())
    n = views_seeing(g.means, scene.cameras.subset(train).scaled(stats["train_scale"]))
    smax = np.exp(g.log_scales).max(1)
    print(f"# {scene.scene_id}: {len(g)} Gaussians; seen by 0 / 1 / >=2 training views: "
          f"{(n == 0).sum()} / {(n == 1).sum()} / {(n >= 2).sum()}; median largest std-dev of "
          f"the one-view ones / all: {np.median(smax[n == 1]):.3g} / {np.median(smax):.3g}")
    print("| model | " + " | ".join(f"held-out view {int(i)}" for i in test) + " | mean |")
    print("|---|" + "---|" * (len(test) + 1))
    for name, keep in [("all", np.ones(len(g), bool)), ("without one-view", n != 1),
                       ("without no-view", n != 0)]:
        ev = evaluate(g.subset(np.flatnonzero(keep)), scene, test, scale=stats["train_scale"])
        print(f"| {name} ({keep.sum()}) | " + " | ".join(f"{p:.2f}" for p in ev["psnr"])
              + f" | {ev['psnr_mean']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
