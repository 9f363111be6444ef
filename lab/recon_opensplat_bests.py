"""Issue 17's "OpenSplat's best within a fifth of its time" read on rows whose OpenSplat runs
are not in the same file: for every run of one arm, the first training CPU-minute at which its
held-out curve reaches OpenSplat's best, and the ratio to the CPU-minutes OpenSplat took.

OpenSplat's best per scene-split is, in order of preference, the median-best of the OpenSplat
rows given (``recon.py --compare opensplat`` rows, e.g. stops 47 and 49's kept every-8th rows),
else the bests quoted in docs/RECON.md's table "OpenSplat's best within a fifth of its time,
the remaining scene-splits under train-only points" (stop 45; its rows were not kept).

    .venv/bin/python -m lab.recon_opensplat_bests ROWS... [--arm new]
"""

from __future__ import annotations

import argparse

from lab.recon_goals import best, read_rows

# stop 45, seed 42, train-only points: (best held-out PSNR, CPU-minutes to it)
STOP45_BESTS = {
    ("dtu_scan24", "every8"): (23.00, 8.64), ("kermit", "every8"): (20.80, 8.59),
    ("llff_fern", "every8"): (21.42, 9.98), ("dtu_scan24", "ood"): (15.82, 9.29),
    ("kermit", "ood"): (18.83, 9.70), ("llff_fern", "ood"): (20.40, 9.51),
    ("strecha_fountain-P11", "ood"): (17.06, 1.98), ("buddha", "ood"): (17.09, 4.80),
}


def opensplat_bests(rows: list[dict]) -> dict[tuple[str, str], tuple[float, float]]:
    """Per (scene, split): the quoted best, replaced by the median-best OpenSplat row given."""
    out = dict(STOP45_BESTS)
    runs: dict[tuple[str, str], list[tuple[float, float]]] = {}
    for r in rows:
        if r["arm"] == "opensplat" and (b := best(r.get("test_psnr_curve") or [])):
            runs.setdefault((r["scene"], r["split"]), []).append(b)
    for key, bs in runs.items():
        out[key] = sorted(bs)[len(bs) // 2]
    return out


def first_reach(rows: list[dict], arm: str = "new") -> list[tuple[str, str, int, float, float,
                                                                   float | None]]:
    """``(scene, split, seed, OpenSplat best, its CPU-minutes, first CPU-minute reaching it or
    None)`` for every row of ``arm`` whose scene-split has an OpenSplat best."""
    bests = opensplat_bests(rows)
    out = []
    for r in sorted((r for r in rows if r["arm"] == arm),
                    key=lambda r: (r["scene"], r["split"], r.get("seed") or 0)):
        if (key := (r["scene"], r["split"])) in bests:
            b, t = bests[key]
            hit = [c["train_cpu_minutes"] for c in r["test_psnr_curve"] if c["test_psnr"] >= b]
            out.append((*key, r.get("seed"), b, t, hit[0] if hit else None))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rows", nargs="+")
    ap.add_argument("--arm", default="new")
    a = ap.parse_args(argv)
    rows = [r for p in a.rows for r in read_rows(p)]
    print("| scene, split | OpenSplat best (CPU-min) | seed | first reach (CPU-min) | ratio |")
    print("|---|---|---|---|---|")
    for scene, split, seed, b, t, hit in first_reach(rows, a.arm):
        print(f"| {scene}, {split} | {b:.2f} ({t:.2f}) | {seed} | "
              + ("never | - |" if hit is None else f"{hit:.2f} | {hit / t:.3f} |"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
