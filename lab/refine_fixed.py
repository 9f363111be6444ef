"""Do fixed free views help refine-3dgs? The arms of docs/REFINE.md on a store made with
``recon_split=ood``, each scene with a fixer that never saw it, scenes run in parallel
processes (one thread each, so CPU seconds stay honest), then the table and the goal test.

    python -m lab.refine_fixed STORE --fixer-map kermit,buddha=F1.pt --fixer-map ...=F2.pt \\
        --default-fixer SHIPPED.pt --seeds 0 1 2 --jobs 2
    python -m lab.refine_fixed STORE ... --table-only

``--fixer-map SCENES=CKPT`` names the checkpoint of those scenes (a fixer trained without
them); scenes not mapped use ``--default-fixer`` (procedural scenes of seeds no fixer saw).
Results are the flow's own (``STORE/scenes/<id>/refine/...``): a re-run reuses finished arms.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

ARMS = ["baseline", "baseline+time", "raw", "fixed", "fixed+conf", "progressive", "oracle"]
GOAL_ARMS = ("fixed+conf", "progressive")


def _config(a, fixer: str | None, n_train: int | None = None):
    from schemas.refine import RefineConfig

    cap = None
    if a.free_share is not None and n_train is not None:  # the trial: pseudo views <= share
        cap = max(1, int(a.free_share * n_train))
    return RefineConfig(arms=a.arms, seeds=a.seeds, fixer=fixer, post_fix=True,
                        max_free_views=cap)


def _one(store: str, scene: str, cfg_json: str, compute: bool) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)
    from freescale_core.downstream.refine import refine_scene, summarize_scene
    from freescale_core.store.reader import FreeViewSet
    from schemas.refine import RefineConfig

    cfg = RefineConfig.model_validate_json(cfg_json)
    out = refine_scene(FreeViewSet.open(store, scene), cfg, compute=compute,
                       log=lambda s: print(s, flush=True))
    return {"summary": summarize_scene(out), "out": out}


def run(a) -> list[dict]:
    from freescale_core.store.reader import open_scenes

    fmap = {}
    for item in a.fixer_map:
        names, _, ckpt = item.partition("=")
        for n in names.split(","):
            fmap[n.strip()] = ckpt
    sets = {f.scene_id: f for f in open_scenes(a.store, a.scenes)}
    scenes = a.scenes or list(sets)
    n_train = {s: int((~sets[s].dataset_views().is_free).sum()) for s in scenes}
    jobs = [(s, _config(a, fmap.get(s, a.default_fixer), n_train[s]).model_dump_json())
            for s in scenes]
    res = {}
    if a.table_only or a.jobs <= 1:
        for s, c in jobs:
            res[s] = _one(a.store, s, c, not a.table_only)
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(a.jobs, mp_context=mp.get_context("spawn")) as ex:
            futs = {ex.submit(_one, a.store, s, c, True): s for s, c in jobs}
            for f in as_completed(futs):
                res[futs[f]] = f.result()
                print(f"[lab] {futs[f]} done", flush=True)
    return [res[s] for s in scenes]


# --------------------------------------------------------------------------- tables
def _f(x, d=2, sign=True):
    if x is None or not np.isfinite(x):
        return ""
    return f"{x:+.{d}f}" if sign else f"{x:.{d}f}"


def scene_table(results: list[dict]) -> str:
    lines = ["| scene | arm | seeds | train views | views added | steps | PSNR | SSIM | d vs baseline (std) "
             "| d vs baseline+time (std) | dSSIM vs +time | CPU overhead | post PSNR | "
             "pseudo view truth PSNR (render -> fixed) |", "|" + "---|" * 14]
    for r in results:
        sm = r["summary"]["summary"]
        for arm, x in sm.items():
            d = f"{_f(x.get('dpsnr'))} ({_f(x.get('dpsnr_std'), 2, False)})" if "dpsnr" in x else ""
            dt = (f"{_f(x.get('dpsnr_time'))} ({_f(x.get('dpsnr_time_std'), 2, False)})"
                  if "dpsnr_time" in x else "")
            tr = ""
            adds = [a for s in r["out"]["arms"][arm].values() for a in s.get("added", [])]
            pg = [a["info"]["pseudo_gt_psnr"] for a in adds if "pseudo_gt_psnr" in a.get("info", {})]
            rg = [a["info"]["render_gt_psnr"] for a in adds if "render_gt_psnr" in a.get("info", {})]
            if pg:
                tr = f"{np.mean(rg):.2f} -> {np.mean(pg):.2f}"
            elif adds and np.isfinite([a.get("gt_psnr", np.nan) for a in adds]).any():
                tr = f"{np.nanmean([a.get('gt_psnr', np.nan) for a in adds]):.2f}"
            co = f"{100 * x['cpu_overhead']:+.0f}%" if "cpu_overhead" in x else ""
            lines.append(
                f"| {r['summary']['scene']} | {arm} | {len(x['seeds'])} | "
                f"{r['summary'].get('n_train_views', '')} | {x['n_added']:.0f} | "
                f"{x['iterations']:.0f} | {x['psnr']:.2f} | {x['ssim']:.3f} | {d} | {dt} | "
                f"{_f(x.get('dssim_time'), 3)} | {co} | {_f(x.get('post_psnr'), 2, False)} | {tr} |")
    return "\n".join(lines)


def goal_table(results: list[dict], procedural: set[str]) -> str:
    """Mean over the real scenes of each arm's paired delta; wins = scenes where the delta
    against baseline+time is > 0; the goal: >= +0.3 dB, >= 8 of 11 wins, SSIM not down."""
    arms = sorted({a for r in results for a in r["summary"]["summary"] if a != "baseline"})
    lines = ["| arm | scenes | mean d vs baseline | mean d vs baseline+time | wins vs +time | "
             "mean dSSIM vs +time | mean post PSNR - PSNR | procedural d vs baseline |",
             "|---|---|---|---|---|---|---|---|"]
    for arm in arms:
        real = [r["summary"]["summary"][arm] for r in results
                if r["summary"]["scene"] not in procedural and arm in r["summary"]["summary"]]
        proc = [r["summary"]["summary"][arm] for r in results
                if r["summary"]["scene"] in procedural and arm in r["summary"]["summary"]]
        m = lambda xs, k: (float(np.mean([x[k] for x in xs]))  # noqa: E731
                           if xs and all(k in x for x in xs) else float("nan"))
        wins = sum(x.get("dpsnr_time", -1) > 0 for x in real)
        post = [x["post_psnr"] - x["psnr"] for x in real if "post_psnr" in x]
        lines.append(f"| {arm} | {len(real)} | {_f(m(real, 'dpsnr'))} | {_f(m(real, 'dpsnr_time'))}"
                     f" | {wins}/{len(real)} | {_f(m(real, 'dssim_time'), 3)} | "
                     f"{_f(float(np.mean(post)) if post else float('nan'))} | "
                     f"{_f(m(proc, 'dpsnr'))} |")
    base = [r["summary"]["summary"]["baseline"] for r in results
            if r["summary"]["scene"] not in procedural and "baseline" in r["summary"]["summary"]]
    post = [x["post_psnr"] - x["psnr"] for x in base if "post_psnr" in x]
    lines.append(f"| baseline (post only) | {len(base)} | | | | | "
                 f"{_f(float(np.mean(post)) if post else float('nan'))} | |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("store")
    p.add_argument("--scenes", nargs="+", default=None)
    p.add_argument("--arms", nargs="+", default=ARMS)
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--fixer-map", action="append", default=[], metavar="SCENES=CKPT")
    p.add_argument("--default-fixer", default=None)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--free-share", type=float, default=None,
                   help="trial: at most this fraction x the training views join as free views "
                   "(sets max_free_views per scene)")
    p.add_argument("--table-only", action="store_true")
    p.add_argument("--json", default=None, help="also write the summaries here")
    a = p.parse_args(argv)
    res = run(a)
    proc = {r["summary"]["scene"] for r in res if r["summary"]["scene"].startswith("sample")}
    print(scene_table(res))
    print()
    print(goal_table(res, proc))
    if a.json:
        Path(a.json).write_text(json.dumps([r["summary"] for r in res], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
