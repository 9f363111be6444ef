"""The trivial held-out baselines beside ``benchmarks/recon.py`` rows: per scene and split, the
held-out PSNR of copying the nearest training photo and of the mean training photo, at the
size the rows' held-out views were scored at (``freescale_core.eval.heldout``).

    FREESCALE_DATASETS=../shared/datasets .venv/bin/python benchmarks/recon_baselines.py rows.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != REPO / "benchmarks"]
sys.path.insert(0, str(REPO))

from benchmarks.recon import load, resolve  # noqa: E402
from freescale_core.eval.heldout import trivial_heldout_baselines  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    ap.add_argument("rows", type=Path, help="rows.jsonl of benchmarks/recon.py --out")
    args = ap.parse_args(argv)
    if not args.rows.is_file():
        ap.error(f"no such rows file: {args.rows}")
    done = set()
    print("| scene | split | held-out size (long side) | nearest photo | mean photo |")
    print("|---|---|---|---|---|")
    for ln in args.rows.read_text().splitlines():
        r = json.loads(ln) if ln.strip() else None
        if not r or "width" not in r or (r["scene"], r["split"]) in done:
            continue  # OpenSplat rows carry no training size
        done.add((r["scene"], r["split"]))
        d = resolve(r["scene"], Path("/nonexistent"))
        if d is None:
            continue
        scene = load(d)
        train, test = scene.split(r["split"])
        side = max(r["width"], r["height"])
        b = trivial_heldout_baselines(scene, train, test, side)
        print(f"| {r['scene']} | {r['split']} | {side} | {b['heldout_nearest_psnr']:.2f} | "
              f"{b['heldout_mean_psnr']:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
