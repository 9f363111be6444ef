"""Benchmark of the refine-3dgs flow: arms x scenes x seeds on a store made with
``recon_split=ood``, printing baseline vs refined held-out PSNR / SSIM (docs/REFINE.md).

    python -m flows.cli run SCENES --store S --preset fast --set recon_split=ood
    python -m benchmarks.refine S --arms baseline wiou --seeds 0 1 2 [--scenes ...] \
        [--set recon.max_iterations=600]

Results are the flow's own (``STORE/scenes/<id>/refine/...``): a re-run reuses finished arms,
so the table can be printed again (``--table-only``) or extended with more arms or seeds.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np




def aggregate(summaries: list[dict], procedural: set[str]) -> str:
    """Mean delta per arm over real and over procedural scenes."""
    lines = ["| arm | scenes | mean dPSNR real | mean dSSIM real | mean dPSNR procedural | "
             "mean off-path dPSNR procedural | median overhead |", "|---|---|---|---|---|---|---|"]
    arms = sorted({a for s in summaries for a in s["summary"] if a != "baseline"})
    for arm in arms:
        rows = [(s["scene"], s["summary"][arm]) for s in summaries
                if arm in s["summary"] and "dpsnr" in s["summary"][arm]]
        real = [r for sc, r in rows if sc not in procedural]
        proc = [r for sc, r in rows if sc in procedural]
        f = lambda xs, k, d=2: (f"{np.mean([x[k] for x in xs]):+.{d}f}"  # noqa: E731
                                if xs and all(k in x for x in xs) else "")
        ov = np.median([r["overhead"] for _, r in rows]) if rows else float("nan")
        lines.append(f"| {arm} | {len(rows)} | {f(real, 'dpsnr')} | {f(real, 'dssim', 3)} | "
                     f"{f(proc, 'dpsnr')} | {f(proc, 'doffpath_psnr')} | {100 * ov:+.0f}% |")
    return "\n".join(lines)


def per_view(out: dict, arm: str) -> list[tuple[int, float, float]]:
    """``(held-out view id, baseline PSNR, arm PSNR)`` per held-out view, means over the
    seeds both arms have."""
    base, other = out["arms"].get("baseline", {}), out["arms"].get(arm, {})
    seeds = [s for s in other if s in base]
    if not seeds:
        return []
    ids = base[seeds[0]]["heldout_view_ids"]
    b = np.mean([base[s]["heldout"]["psnr"] for s in seeds], 0)
    o = np.mean([other[s]["heldout"]["psnr"] for s in seeds], 0)
    return [(int(i), float(x), float(y)) for i, x, y in zip(ids, b, o)]


def main(argv=None) -> int:
    from flows.cli import _parse_set
    from flows.refine_3dgs import format_table
    from freescale_core.downstream.refine import refine_scene, summarize_scene
    from freescale_core.store.reader import open_scenes
    from schemas.refine import RefineConfig, refine_recon_config

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("store")
    p.add_argument("--scenes", nargs="+", default=None)
    p.add_argument("--arms", nargs="+", default=["baseline", "wiou"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--json", default=None, help="also write the summaries here")
    p.add_argument("--views", action="store_true", help="also print every held-out view")
    p.add_argument("--table-only", action="store_true",
                   help="train nothing: the table of the arms already finished")
    a = p.parse_args(argv)
    over = _parse_set(a.set)
    r = over.get("recon", {})
    if "max_iterations" in r:  # a fixed budget, as `freescale refine` does
        r.setdefault("min_iterations", r["max_iterations"])
    over["recon"] = {**refine_recon_config().model_dump(mode="json"), **r}
    cfg = RefineConfig.model_validate({**over, "arms": a.arms, "seeds": a.seeds})
    print(f"# refine benchmark: {a.store}, arms {cfg.arm_names()}, seeds {cfg.seeds}, "
          f"{cfg.recon.max_iterations} steps, free views join at {cfg.schedule()}", flush=True)
    t0 = time.perf_counter()
    summaries, procedural, views = [], set(), []
    for fvs in open_scenes(a.store, a.scenes):
        out = refine_scene(fvs, cfg, log=lambda s: print(s, flush=True),
                           compute=not a.table_only)
        s = summarize_scene(out)
        summaries.append(s)
        for arm in out["arms"]:
            if arm != "baseline":
                for vid, pb, pa in per_view(out, arm):
                    views.append((s["scene"], arm, vid, pb, pa))
        if any("offpath" in m for by in out["arms"].values() for m in by.values()):
            procedural.add(s["scene"])
        print(f"# {s['scene']}: computed {len(out['computed'])}, reused {len(out['reused'])}, "
              f"{time.perf_counter() - t0:.0f} s so far", flush=True)
    print()
    print(format_table(summaries))
    print()
    print(aggregate(summaries, procedural))
    if a.views:
        print("\n| scene | arm | held-out view | baseline PSNR | arm PSNR | delta |\n"
              "|---|---|---|---|---|---|")
        for sc, arm, vid, pb, pa in views:
            print(f"| {sc} | {arm} | {vid} | {pb:.2f} | {pa:.2f} | {pa - pb:+.2f} |")
    if a.json:
        Path(a.json).write_text(json.dumps(summaries, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
