"""How much of a learned background's gain is the colour, and how much the Gaussians.

Given two models of one scene and split saved by ``benchmarks/recon.py --save-dir`` (``A``
trained on a fixed background, ``B`` with ``background_lr``), scores both on the held-out views:
each on its own background and on the other's, over all pixels, over the pixels both models
cover (accumulated opacity >= ``--alpha`` in both renders) and over the rest.

    FREESCALE_DATASETS=../shared/datasets .venv/bin/python -m lab.recon_background \\
        SCENE SPLIT DIR_A DIR_B        # DIR_* = SAVE_DIR/ARM/SPLIT/SCENE_ID (gaussians.ply)

If B's gain over A survives on the covered pixels, the Gaussians changed; if A on B's colour
catches up with B, the colour alone explains it.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from benchmarks.recon import load, resolve


def coverage_masks(models, scene, test, scale: float, alpha_min: float) -> list[np.ndarray]:
    """Per held-out view, the pixels every model covers (alpha >= ``alpha_min``)."""
    from freescale_core.raster import render_gaussians

    cams = scene.cameras.subset(np.asarray(test)).scaled(scale)
    out = []
    for j in range(len(test)):
        m = None
        for g in models:
            _, _, a = render_gaussians(g, cams.world_from_cam[j], cams.fx[j], cams.fy[j],
                                       cams.cx[j], cams.cy[j], int(cams.width[j]),
                                       int(cams.height[j]))
            m = (a >= alpha_min) if m is None else (m & (a >= alpha_min))
        out.append(m)
    return out


def score(g, scene, test, scale, bg, masks=None) -> float:
    """Mean held-out PSNR; with ``masks``, over the views whose mask has a pixel (NaN if none)."""
    from freescale_core.recon.trainer import evaluate

    if masks is not None:
        keep = [j for j, m in enumerate(masks) if m.any()]
        if not keep:
            return float("nan")
        test, masks = [test[j] for j in keep], [masks[j] for j in keep]
    return float(evaluate(g, scene, test, scale=scale, background=bg, masks=masks)["psnr_mean"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("split")
    ap.add_argument("a", type=Path, help="model dir of the fixed-background arm")
    ap.add_argument("b", type=Path, help="model dir of the learned-background arm")
    ap.add_argument("--alpha", type=float, default=0.5)
    args = ap.parse_args(argv)
    from freescale_core.scene.ply import read_background, read_ply

    with tempfile.TemporaryDirectory() as tmp:
        d = resolve(args.scene, Path(tmp))
        if d is None:
            return 1
        scene = load(d)
        _, test = scene.split(args.split)
        arms = {}
        for name, p in (("A", args.a), ("B", args.b)):
            st = json.loads((p / "recon_stats.json").read_text())
            arms[name] = (read_ply(p / "gaussians.ply"),
                          read_background(p / "gaussians.ply", tuple(st["background"])),
                          float(st["train_scale"]))
        scale = arms["A"][2]
        if arms["B"][2] != scale:
            raise SystemExit(f"{args.scene}: the two models were trained at different scales")
        cov = coverage_masks([arms["A"][0], arms["B"][0]], scene, test, scale, args.alpha)
        rest = [~m for m in cov]
        share = float(np.mean([m.mean() for m in cov]))
        print(f"# {scene.scene_id} {args.split}: {len(test)} held-out views, "
              f"{100 * share:.1f}% of their pixels covered by both (alpha >= {args.alpha:g}); "
              f"A's background {np.round(arms['A'][1], 3).tolist()}, "
              f"B's {np.round(arms['B'][1], 3).tolist()}")
        print("| model | background | all pixels | covered by both | the rest |")
        print("|---|---|---|---|---|")
        for name in ("A", "B"):
            g = arms[name][0]
            for bname in ("A", "B"):
                bg = arms[bname][1]
                row = [score(g, scene, test, scale, bg),
                       score(g, scene, test, scale, bg, cov) if share > 0 else float("nan"),
                       score(g, scene, test, scale, bg, rest) if share < 1 else float("nan")]
                print(f"| {name} | {bname}'s {np.round(bg, 2).tolist()} | "
                      + " | ".join(f"{v:.2f}" for v in row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
