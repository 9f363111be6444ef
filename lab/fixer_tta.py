"""Test-time fine-tuning of the fixer on the target scene's own leave-out pairs.

For a scene and a split (``every8`` / ``ood``), the pairs used to fine-tune are made inside
that split's *training* views only (a nested split of ``scene.subset(train)``). So the split's
held-out photos, which are the evaluation targets, are never a target, a warped reference or a
training view of the fine-tuning. The fold's fixer (trained without the scene) is
fine-tuned on those pairs (``init_from``) and then scored, beside the fold's fixer untouched,
on the scene's held-out pairs of the same split (final reconstructions). The CPU seconds of
the pairs and of the fine-tuning are the cost.

    python -m lab.fixer_tta --scenes ../shared/datasets/kermit ... --base OUT/fixer_s0_f0/fixer.pt \
        --pairs PAIRS --out OUT_TTA --steps 200
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def run(a) -> list[dict]:
    from freescale_core.eval.fixer_pairs import make_fold_pairs
    from freescale_core.fixer.data import load_pairs, write_pair_folder
    from freescale_core.fixer.train import train_fixer
    from freescale_core.scene.io import load_scene
    from lab.fixer_kfold import score_pairs
    from schemas.fixer import FixerTrainConfig
    from schemas.fixer_pairs import PairsConfig

    out = Path(a.out)
    rows = []
    for path in a.scenes:
        path = Path(path)
        scene = load_scene(path, cache_dir=str(out / ".cache"))
        for split in a.splits:
            tr, te = scene.split(split)
            sub = scene.subset(tr)
            sub.extras.pop("heldout_names", None)  # its nested split is by rule, not the list
            held = {scene.image_names[int(i)] for i in te}
            assert not held & set(sub.image_names), "a held-out photo in the fine-tuning scene"
            sid = f"{scene.scene_id}@{split}"
            c0 = time.process_time()
            for sub_fold in ("every8", "ood"):
                folder = out / "pairs" / sid / sub_fold
                if (folder / "done.json").is_file():
                    continue
                samples, facts = make_fold_pairs(sub, sub_fold, PairsConfig(), seed=0)
                for s in samples:
                    s.meta["scene_id"] = sid
                write_pair_folder(folder, samples, {"facts": facts})
            pairs_cpu = time.process_time() - c0
            run_dir = out / "runs" / sid
            cfg = FixerTrainConfig(steps=a.steps, init_from=str(a.base), warmup_steps=0,
                                   lr=a.lr)
            c1 = time.process_time()
            train_fixer(out / "pairs", run_dir, cfg, train_scenes=[sid],
                        resume=run_dir.exists(), log=None)
            tune_cpu = time.process_time() - c1
            ev = [s for s in load_pairs(a.pairs, scenes=[scene.scene_id])
                  if s.meta["budget"] == 1.0 and s.meta["fold"] == split]
            base = score_pairs(str(a.base), ev, "base", 0, split)
            tuned = score_pairs(str(run_dir / "fixer.pt"), ev, "tta", 0, split)
            r = {"scene_id": scene.scene_id, "split": split, "views": len(ev),
                 "psnr_raw": float(np.mean([x["psnr_raw"] for x in base])),
                 "d_base": float(np.mean([x["psnr_fixed"] - x["psnr_raw"] for x in base])),
                 "d_tta": float(np.mean([x["psnr_fixed"] - x["psnr_raw"] for x in tuned])),
                 "dssim_base": float(np.mean([x["ssim_fixed"] - x["ssim_raw"] for x in base])),
                 "dssim_tta": float(np.mean([x["ssim_fixed"] - x["ssim_raw"] for x in tuned])),
                 "pairs_cpu_s": round(pairs_cpu, 1), "tune_cpu_s": round(tune_cpu, 1)}
            rows.append(r)
            print(json.dumps(r), flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", required=True)
    ap.add_argument("--splits", nargs="+", default=["every8", "ood"])
    ap.add_argument("--base", required=True, help="the fold's fixer.pt (never saw the scenes)")
    ap.add_argument("--pairs", required=True, help="pairs folder with the scenes' held-out pairs")
    ap.add_argument("--out", required=True)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--lr", type=float, default=5e-4)
    a = ap.parse_args(argv)
    rows = run(a)
    print("\n| scene | split | views | raw PSNR | fold fixer d | + fine-tuning d | dSSIM base / "
          "tuned | CPU s (pairs + tuning) |\n|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene_id']} | {r['split']} | {r['views']} | {r['psnr_raw']:.2f} | "
              f"{r['d_base']:+.2f} | {r['d_tta']:+.2f} | {r['dssim_base']:+.3f} / "
              f"{r['dssim_tta']:+.3f} | {r['pairs_cpu_s']:.0f} + {r['tune_cpu_s']:.0f} |")
    print(f"| **mean** | | | | {np.mean([r['d_base'] for r in rows]):+.2f} | "
          f"{np.mean([r['d_tta'] for r in rows]):+.2f} | | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
