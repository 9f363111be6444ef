"""Co-visibility of held-out views (``freescale_core.eval.covis``): the reference models and masks.

``ref`` trains the ``cpu`` preset on *every* view of a scene (held-out ones included) and saves
``OUT/<scene>/gaussians.ply``: the geometry the masks are cut with, never a scored arm.
``masks`` prints, per held-out view of a split, the share of its pixels some training view
saw, and with ``--png`` writes the views with the unseen pixels tinted red. ``check`` measures
the masks of a reference against the oracle's exact masks on a sample scene.

    FREESCALE_DATASETS=../shared/datasets .venv/bin/python -m lab.covis ref buddha \\
        --seed 0 --cpu-minutes 10 --threads 1 --out covis_ref
    FREESCALE_DATASETS=../shared/datasets .venv/bin/python -m lab.covis masks buddha \\
        --ref covis_ref --split ood --png covis_buddha.png
    .venv/bin/python -m lab.covis ref sample --out covis_ref && \\
        .venv/bin/python -m lab.covis check sample --ref covis_ref
    # then: benchmarks/recon.py ... --covis-ref covis_ref  (held-out PSNR on co-visible pixels)
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

from benchmarks.recon import COVIS_REL_TOL as REL_TOL
from benchmarks.recon import COVIS_SEARCH_PX as SEARCH_PX
from benchmarks.recon import (load, load_covis_reference, oracle_covis, resolve,
                              train_scale)
from freescale_core.eval.covis import split_masks
from schemas.recon import ReconConfig


def cmd_ref(a) -> int:
    from freescale_core.recon.trainer import reconstruct
    from freescale_core.scene.ply import write_ply

    cfg = ReconConfig.cpu().model_copy(update={"max_seconds": 60.0 * a.cpu_minutes,
                                               "threads": a.threads})
    with tempfile.TemporaryDirectory(prefix="freescale_covis_") as tmp:
        d = resolve(a.scene, Path(tmp))
        if d is None:
            return 1
        scene = load(d)
        t = time.perf_counter()
        res = reconstruct(scene, ReconConfig.model_validate(cfg.model_dump()), seed=a.seed,
                          clock="cpu")
        out = a.out / scene.scene_id
        out.mkdir(parents=True, exist_ok=True)
        write_ply(out / "gaussians.ply", res.gaussians)
        st = res.stats
        (out / "reference.json").write_text(json.dumps(
            {"scene": scene.scene_id, "seed": a.seed, "cpu_minutes": a.cpu_minutes,
             "views": len(scene.cameras), "iterations": st["iterations"],
             "train_psnr": st["recon_train_psnr"], "n_gaussians": st["n_gaussians"]}, indent=1))
        print(f"{scene.scene_id}: reference on all {len(scene.cameras)} views, "
              f"{st['iterations']} steps, {time.perf_counter() - t:.0f} s, train PSNR "
              f"{st['recon_train_psnr']:.2f} dB -> {out / 'gaussians.ply'}")
    return 0


def cmd_masks(a) -> int:
    with tempfile.TemporaryDirectory(prefix="freescale_covis_") as tmp:
        d = resolve(a.scene, Path(tmp))
        if d is None:
            return 1
        scene = load(d)
        scale = train_scale(d, a.split)
        ms = split_masks(scene, a.split, scale, load_covis_reference(a.ref, scene.scene_id),
                         a.rel_tol, search_px=a.search_px)
        _, test = scene.split(a.split)
        print(f"| {scene.scene_id} {a.split} view | co-visible share |")
        print("|---|---|")
        for i, m in zip(test, ms):
            print(f"| {scene.image_names[int(i)]} "
                  f"| {m.mean():.1%} |")
        print(f"| mean | {np.mean([m.mean() for m in ms]):.1%} |")
        if a.png:
            import cv2

            from freescale_core.recon.trainer import _resize

            te = scene.cameras.subset(test).scaled(scale)
            tiles = []
            for j, (i, m) in enumerate(zip(test, ms)):
                img = _resize(scene.load_image(int(i)), int(te.width[j]), int(te.height[j]))
                img = img.astype(np.float32)
                img[~m] = 0.45 * img[~m] + 0.55 * np.array([255.0, 0.0, 0.0])
                tiles.append(img.astype(np.uint8))
            cv2.imwrite(str(a.png), cv2.cvtColor(np.concatenate(tiles, 1), cv2.COLOR_RGB2BGR))
            print(f"wrote {a.png} (unseen pixels tinted red)")
    return 0


def cmd_check(a) -> int:
    with tempfile.TemporaryDirectory(prefix="freescale_covis_") as tmp:
        d = resolve(a.scene, Path(tmp))
        if d is None or not (d / "scene.json").is_file():
            raise SystemExit("check needs a sample or family scene (its oracle gives the exact "
                             "masks)")
        scene = load(d)
        scale = train_scale(d, a.split)
        train, test = scene.split(a.split)
        _, depths, exact = oracle_covis(d, scene, train, test, scale)
        solid = [dd > 0 for dd in depths]
        unseen = np.concatenate([~e[s] for e, s in zip(exact, solid)])
        ref = load_covis_reference(a.ref, scene.scene_id)
        print(f"# {scene.scene_id} {a.split}: {len(test)} held-out views at scale {scale:.3f}; "
              f"off the sky, the oracle has {unseen.mean():.1%} of the pixels unseen")
        print("| rel_tol | search px | agreement | unseen pixels found | called co-visible | "
              "of those, truly co-visible |")
        print("|---|---|---|---|---|---|")
        for tol in a.rel_tols:
            for sp in a.search_px:
                ms = split_masks(scene, a.split, scale, ref, tol, search_px=sp)
                found = np.concatenate([~m[s] for m, s in zip(ms, solid)])
                hit = (found & unseen).sum()
                pure = (~found & ~unseen).sum() / max((~found).sum(), 1)
                print(f"| {tol:g} | {sp} | {(found == unseen).mean():.1%} | "
                      f"{hit / max(unseen.sum(), 1):.1%} | {1 - found.mean():.1%} | "
                      f"{pure:.1%} |")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("ref", help="train the reference model on every view")
    r.add_argument("scene")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--cpu-minutes", type=float, default=10.0)
    r.add_argument("--threads", type=int, default=1)
    r.add_argument("--out", type=Path, required=True)
    for name, fn in (("masks", cmd_masks), ("check", cmd_check)):
        m = sub.add_parser(name)
        m.add_argument("scene")
        m.add_argument("--ref", type=Path, required=True)
        m.add_argument("--split", default="ood", choices=["ood", "every8"])
        m.set_defaults(fn=fn)
    sub.choices["masks"].add_argument("--rel-tol", type=float, default=REL_TOL)
    sub.choices["masks"].add_argument("--png", type=Path, default=None)
    sub.choices["check"].add_argument("--rel-tols", type=float, nargs="+",
                                      default=[0.02, 0.05, 0.1, 0.2])
    sub.choices["check"].add_argument("--search-px", type=int, nargs="+", default=[0, 1, 2])
    sub.choices["masks"].add_argument("--search-px", type=int, default=SEARCH_PX)
    r.set_defaults(fn=cmd_ref)
    a = ap.parse_args(argv)
    return a.fn(a)


if __name__ == "__main__":
    raise SystemExit(main())
