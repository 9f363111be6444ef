"""The fixer on scenes it never saw: k-fold over scenes, seeds, baselines and ablations.

For each fold (a group of scenes) and seed a fixer is trained on the pairs of every other
scene (``freescale_core.fixer.train.train_fixer``, same config and budget for every arm) and
scored on the held-out scenes' pairs of the *final* reconstructions (budget 1.0): the raw
render (``none``), ``reproject`` (the nearest photo warped and blended, the existing
rectifier) and the fixer, PSNR / SSIM against the held-out photos, which neither the
reconstruction nor the fixer saw. Procedural scenes of unseen seeds (``--eval-pairs``): the
oracle fold (off-path poses, exact truth), raw -> fixed, and the Spearman correlation of the
per-view mean confidence with the per-view error.

Rows (one per arm, seed and pair) go to ``OUT/rows.jsonl``; the table is printed from them::

    python -m lab.fixer_kfold --pairs PAIRS --eval-pairs PAIRS_EVAL --out OUT \\
        --fold kermit,buddha --fold dtu_scan24 --seeds 0 1 2 --steps 600
    python -m lab.fixer_kfold --out OUT --table       # print the table again
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from freescale_core.fixer.data import load_pairs


def _score(img, ref, mask):
    from freescale_core.eval.fixer_score import score_images

    return score_images(img, ref, mask)


def score_pairs(model_path: str | None, samples, arm: str, seed: int, fold: str) -> list[dict]:
    """Rows for ``samples`` fixed by the checkpoint (and the raw / reproject baselines)."""
    from freescale_core.fixer.infer import fix_samples
    from freescale_core.fixer.model import load_fixer
    from freescale_core.freeviews.rectify_image import ReprojectRectifier

    model, meta = load_fixer(model_path)
    rect = ReprojectRectifier()
    rows = []
    for s, (f, c) in zip(samples, fix_samples(model, samples)):
        rep, _ = rect.blend(s.render, s.warps[0], s.warp_weight[0]) if s.k else (s.render, None)
        pr, sr = _score(s.render, s.target, s.mask)
        pf, sf = _score(f, s.target, s.mask)
        pp, sp = _score(rep, s.target, s.mask)
        err = float(np.abs(f - s.target)[s.mask].mean())
        rows.append({"arm": arm, "seed": seed, "fold": fold, "scene_id": s.meta["scene_id"],
                     "pair_fold": s.meta["fold"], "pair_id": s.meta["pair_id"],
                     "source": s.meta["source"], "psnr_raw": pr, "psnr_fixed": pf,
                     "psnr_reproject": pp, "ssim_raw": sr, "ssim_fixed": sf,
                     "ssim_reproject": sp, "conf_mean": float(c[s.mask].mean()),
                     "err_fixed": err, "train_cpu_s": meta.get("cpu_seconds")})
    return rows


def run(a) -> None:
    from freescale_core.fixer.train import train_fixer
    from schemas.fixer import FixerTrainConfig

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows_path = out / "rows.jsonl"
    done = set()
    if rows_path.is_file():
        for line in rows_path.read_text().splitlines():
            r = json.loads(line)
            done.add((r["arm"], r["seed"], r["fold"]))
    over = json.loads(a.config) if a.config else {}
    arms = {"fixer": {}, "render_only": {"model": {"k": 0}}}
    arms = {k: v for k, v in arms.items() if k in a.arms}
    jobs = []
    for fi, fold in enumerate(a.fold):
        seeds = a.seeds if fi == 0 else a.seeds[:1]
        for arm in arms:
            for seed in (seeds if arm == "fixer" else a.seeds[:1]):
                jobs.append((arm, seed, fold))
    if a.eval_pairs:
        jobs.append(("fixer", a.seeds[0], "all"))
    for arm, seed, fold in jobs:
        if (arm, seed, fold) in done:
            print(f"{arm} seed {seed} fold {fold}: done, kept", flush=True)
            continue
        held = [] if fold == "all" else fold.split(",")
        cfgd = json.loads(json.dumps(over))
        for key, val in arms[arm].items():
            cfgd.setdefault(key, {}).update(val) if isinstance(val, dict) else None
        cfgd["seed"] = seed
        cfg = FixerTrainConfig.model_validate(cfgd)
        run_dir = out / f"{arm}_s{seed}_{'all' if fold == 'all' else 'f' + str(a.fold.index(fold))}"
        t0 = time.process_time()
        train_fixer(a.pairs, run_dir, cfg, holdout_scenes=held, resume=run_dir.exists(),
                    log=lambda s: print(s, flush=True))
        cpu = time.process_time() - t0
        if fold == "all":
            samples = [s for s in load_pairs(a.eval_pairs) if s.meta["budget"] == 1.0]
        else:
            samples = [s for s in load_pairs(a.pairs, scenes=held) if s.meta["budget"] == 1.0]
        rows = score_pairs(str(run_dir / "fixer.pt"), samples, arm, seed, fold)
        for r in rows:
            r["train_cpu_s"] = round(cpu, 1)
        with open(rows_path, "a") as f:
            for r in rows:
                f.write(json.dumps(r) + "\n")
        print(f"{arm} seed {seed} fold {fold}: {len(rows)} pairs scored, train {cpu:.0f} CPU-s",
              flush=True)


def table(out: str | Path) -> None:
    from freescale_core.eval.fixer_score import spearman

    rows = [json.loads(x) for x in (Path(out) / "rows.jsonl").read_text().splitlines()]
    real = [r for r in rows if r["fold"] != "all"]
    print("Held-out photos of scenes the fixer never saw (final reconstructions; mean over "
          "held-out views of both splits; d = method - raw, fixer: mean +- sd over seeds)\n")
    print(f"| scene | views | raw PSNR | reproject d | fixer d | render-only d | raw SSIM | "
          f"reproject dSSIM | fixer dSSIM |")
    print("|---|---|---|---|---|---|---|---|---|")
    scenes = sorted({r["scene_id"] for r in real})
    means = {"rep": [], "fix": [], "ro": [], "srep": [], "sfix": []}
    for sc in scenes:
        R = [r for r in real if r["scene_id"] == sc]
        fx = [r for r in R if r["arm"] == "fixer"]
        ro = [r for r in R if r["arm"] == "render_only"]
        s0 = min(r["seed"] for r in fx)
        base = [r for r in fx if r["seed"] == s0]
        raw = np.mean([r["psnr_raw"] for r in base])
        rep = np.mean([r["psnr_reproject"] - r["psnr_raw"] for r in base])
        per_seed = [np.mean([r["psnr_fixed"] - r["psnr_raw"] for r in fx if r["seed"] == s])
                    for s in sorted({r["seed"] for r in fx})]
        sfix = np.mean([r["ssim_fixed"] - r["ssim_raw"] for r in fx])
        srep = np.mean([r["ssim_reproject"] - r["ssim_raw"] for r in base])
        rod = np.mean([r["psnr_fixed"] - r["psnr_raw"] for r in ro]) if ro else math.nan
        sd = f" +- {np.std(per_seed):.2f}" if len(per_seed) > 1 else ""
        print(f"| {sc} | {len(base)} | {raw:.2f} | {rep:+.2f} | {np.mean(per_seed):+.2f}{sd} | "
              f"{rod:+.2f} | {np.mean([r['ssim_raw'] for r in base]):.3f} | {srep:+.3f} | "
              f"{sfix:+.3f} |")
        means["rep"].append(rep)
        means["fix"].append(np.mean(per_seed))
        means["ro"].append(rod)
        means["srep"].append(srep)
        means["sfix"].append(sfix)
    print(f"| **mean of {len(scenes)}** | | | {np.mean(means['rep']):+.2f} | "
          f"**{np.mean(means['fix']):+.2f}** | {np.nanmean(means['ro']):+.2f} | | "
          f"{np.mean(means['srep']):+.3f} | {np.mean(means['sfix']):+.3f} |")
    print(f"\nscenes below -0.2 dB: {[s for s, d in zip(scenes, means['fix']) if d < -0.2]}")
    proc = [r for r in rows if r["fold"] == "all"]
    if proc:
        print("\nProcedural scenes of unseen seeds, off-path poses vs the exact renderer "
              "(fixer trained on every training scene):\n")
        print("| scene | views | raw PSNR | fixed PSNR | d | reproject d | conf Spearman |")
        print("|---|---|---|---|---|---|---|")
        ds, sps = [], []
        for sc in sorted({r["scene_id"] for r in proc}):
            R = [r for r in proc if r["scene_id"] == sc and r["pair_fold"] == "oracle"]
            if not R:
                continue
            raw, fix = np.mean([r["psnr_raw"] for r in R]), np.mean([r["psnr_fixed"] for r in R])
            rep = np.mean([r["psnr_reproject"] for r in R])
            sp = -spearman([r["conf_mean"] for r in R], [r["err_fixed"] for r in R])
            ds.append(fix - raw)
            sps.append(sp)
            print(f"| {sc} | {len(R)} | {raw:.2f} | {fix:.2f} | {fix - raw:+.2f} | "
                  f"{rep - raw:+.2f} | {sp:.2f} |")
        allR = [r for r in proc if r["pair_fold"] == "oracle"]
        sp_all = -spearman([r["conf_mean"] for r in allR], [r["err_fixed"] for r in allR])
        print(f"| **mean of {len(ds)}** | | | | **{np.mean(ds):+.2f}** | | "
              f"{np.mean(sps):.2f} (pooled {sp_all:.2f}) |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", help="pairs folder of the real + procedural training scenes")
    ap.add_argument("--eval-pairs", default=None, help="pairs of unseen procedural scenes")
    ap.add_argument("--out", required=True)
    ap.add_argument("--fold", action="append", default=[], help="comma-separated scenes")
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--arms", nargs="+", default=["fixer", "render_only"])
    ap.add_argument("--config", default=None, help="FixerTrainConfig overrides as JSON")
    ap.add_argument("--table", action="store_true", help="only print the table")
    a = ap.parse_args(argv)
    if not a.table:
        run(a)
    table(a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
