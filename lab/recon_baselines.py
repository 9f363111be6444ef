"""The trivial held-out baselines beside ``benchmarks/recon.py`` rows: per scene and split, the
held-out PSNR of copying the nearest training photo and of the mean training photo, at the
size the rows' held-out views were scored at (``freescale_core.eval.heldout``).

    FREESCALE_DATASETS=../shared/datasets .venv/bin/python -m lab.recon_baselines rows.jsonl

Rows of ``recon.py --covis-ref DIR`` also get both baselines on the co-visible pixels (the same
reference model's masks).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from benchmarks.recon import (COVIS_REL_TOL, COVIS_SEARCH_PX, load,
                              load_covis_reference, resolve)
from lab.recon_goals import read_rows
from freescale_core.eval.heldout import trivial_heldout_baselines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("rows", type=Path, help="rows.jsonl of benchmarks/recon.py --out")
    args = ap.parse_args(argv)
    if not args.rows.is_file():
        ap.error(f"no such rows file: {args.rows}")
    done = set()
    print("| scene | split | held-out size (long side) | nearest photo | mean photo | "
          "co-visible pixels: nearest / mean |")
    print("|---|---|---|---|---|---|")
    for r in read_rows(args.rows):
        if "width" not in r or (r["scene"], r["split"]) in done:
            continue  # OpenSplat rows carry no training size
        done.add((r["scene"], r["split"]))
        d = resolve(r["scene"], Path("/nonexistent"))
        if d is None:
            continue
        scene = load(d)
        train, test = scene.split(r["split"])
        side = max(r["width"], r["height"])
        b = trivial_heldout_baselines(scene, train, test, side)
        cv = ""
        if r.get("covis_ref"):
            from freescale_core.eval.covis import split_masks

            long = np.maximum(scene.cameras.width[test], scene.cameras.height[test]).max()
            ms = split_masks(scene, r["split"], float(min(1.0, side / long)),
                             load_covis_reference(Path(r["covis_ref"]), scene.scene_id),
                             COVIS_REL_TOL, search_px=COVIS_SEARCH_PX)
            c = trivial_heldout_baselines(scene, train, test, side, ms)
            cv = f"{c['heldout_nearest_psnr']:.2f} / {c['heldout_mean_psnr']:.2f}"
        print(f"| {r['scene']} | {r['split']} | {side} | {b['heldout_nearest_psnr']:.2f} | "
              f"{b['heldout_mean_psnr']:.2f} | {cv} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
