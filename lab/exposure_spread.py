"""How much the training views' exposure differs, per scene and split: the number the trainer's
``exposure_min_gain_std`` rule reads (``freescale_core.recon.photometric``).

    FREESCALE_DATASETS=../shared/datasets .venv/bin/python -m lab.exposure_spread \
        [SCENE ...] [--splits ood every8] [--threshold 0.05]

Prints a markdown table: per scene and split, the training views measured, the sparse points,
the standard deviation of the per-view log colour gains (mean of R, G, B), their range, and
whether the rule at ``--threshold`` corrects exposure. Images are read as the ``cpu`` preset
trains on them (long side <= 512).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np


from freescale_core.recon.photometric import gain_spread, view_log_gains
from freescale_core.recon.trainer import prepare
from freescale_core.scene.io import load_scene
from schemas.recon import ReconConfig

SCENES = ["buddha", "dtu_scan24", "kermit", "llff_fern", "strecha_fountain-P11"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenes", nargs="*", default=SCENES)
    ap.add_argument("--splits", nargs="+", default=["ood", "every8"], choices=["ood", "every8"])
    ap.add_argument("--threshold", type=float, default=0.05)
    a = ap.parse_args(argv)
    root = Path(os.environ.get("FREESCALE_DATASETS",
                               Path(__file__).resolve().parents[2] / "shared" / "datasets"))
    cfg = ReconConfig.cpu().model_copy(update=dict(init_triangulate_below=None))
    print("| scene | split | views measured | sparse points | log-gain std | range (max - min) "
          f"| corrected at {a.threshold:g} |")
    print("|---|---|---|---|---|---|---|")
    for name in a.scenes:
        d = root / name if not Path(name).is_dir() else Path(name)
        scene = load_scene(d)
        for split in a.splits:
            train = scene.split(split)[0]
            data = prepare(scene, cfg, train)
            g = view_log_gains(data.cams, data.images, data.points_xyz, data.points_rgb)
            ok = np.isfinite(g).all(1)
            s = gain_spread(g)
            rng = float((g[ok].max(0) - g[ok].min(0)).mean()) if ok.any() else float("nan")
            print(f"| {scene.scene_id} | {split} | {int(ok.sum())} of {len(g)} | "
                  f"{len(data.points_xyz)} | {'-' if s is None else f'{s:.3f}'} | {rng:.3f} | "
                  f"{'yes' if s is not None and s > a.threshold else 'no'} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
