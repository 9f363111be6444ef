"""``freescale fixer pairs|score`` and ``freescale train-fixer PAIRS OUT``: the image fixer's
training pairs, its scores and its training flow (docs/FIXER.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from flows.cli.common import _parse_set


def add_fixer_parser(sub) -> None:
    """``freescale fixer pairs|score``."""
    fx = sub.add_parser("fixer", help="the image fixer: training pairs, scores").add_subparsers(
        dest="sub", required=True)
    s = fx.add_parser("pairs", help="make fixer training pairs from scene folders "
                      "(leave-out renders + warped nearby photos -> held-out photo)")
    s.add_argument("scenes", nargs="+", help="scene folders (COLMAP, transforms.json, "
                   "procedural); globs are expanded by the shell")
    s.add_argument("--out", required=True, help="pairs folder (PAIRS/<scene>/<fold>/)")
    s.add_argument("--seed", type=int, default=0, help="reconstruction seed")
    s.add_argument("--force", action="store_true", help="remake folds that are up to date")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a PairsConfig field (schemas/fixer_pairs.py), e.g. "
                        "--set max_views_per_fold=6 --set 'folds=[\"every8\"]'")
    s.set_defaults(fn=cmd_fixer_pairs)
    add_score_parser(fx)


def add_score_parser(fx) -> None:
    s = fx.add_parser("score", help="held-out PSNR / SSIM of the raw render, reproject and the "
                      "fixer at a store's held-out cameras (and free views vs the oracle on "
                      "procedural scenes)")
    s.add_argument("store")
    s.add_argument("--scenes", nargs="+", default=None, help="scene ids (None: every ok scene)")
    s.add_argument("--checkpoint", default=None, help="a fixer.pt (None: the shipped one)")
    s.add_argument("--long-side", type=int, default=256, help="scored at this long side (px)")
    s.add_argument("--max-views", type=int, default=0, help="at most this many held-out views "
                   "per scene, evenly spaced (0: all)")
    s.add_argument("--json", action="store_true", help="one JSON object per scene")
    s.set_defaults(fn=cmd_fixer_score)


def cmd_fixer_score(a) -> int:
    from freescale_core.errors import FreeScaleError
    from freescale_core.fixer.model import FixerCheckpointError
    from freescale_core.freeviews.rectify_image import FixerRectifier
    from freescale_core.eval.fixer_score import score_scene
    from freescale_core.store.store import Store

    if not (Path(a.store) / "scenes").is_dir():
        print(f"error: {a.store} is not a store (no scenes/ folder)", file=sys.stderr)
        return 2
    try:
        fixer = FixerRectifier(a.checkpoint)
    except FixerCheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    st = Store(a.store)
    ids = a.scenes or [s for s in st.scene_ids() if st.read_status(s).get("status") == "ok"]
    known = set(st.scene_ids())
    rc = 0
    if not a.json:
        print(f"{'scene':<24} {'split':<6} {'views':>5}  {'PSNR raw':>8} {'reproj':>7} "
              f"{'fixed':>7} {'d':>6}   {'SSIM raw':>8} {'fixed':>6}  oracle raw->fixed")
    for sid in ids:
        if sid not in known:
            print(f"error: scene '{sid}' is not in {a.store}", file=sys.stderr)
            rc = 1
            continue
        try:
            r = score_scene(a.store, sid, fixer, a.long_side, a.max_views)
        except (FreeScaleError, FileNotFoundError) as e:
            print(f"error: {e}", file=sys.stderr)
            rc = 1
            continue
        if a.json:
            r = {k: v for k, v in r.items() if k != "heldout_psnr_per_view"}
            print(json.dumps(r, default=float))
            continue
        orc = (f"{r['oracle_psnr_raw']:.2f} -> {r['oracle_psnr_fixed']:.2f}"
               if "oracle_psnr_raw" in r else "")
        print(f"{sid:<24} {r['recon_split']:<6} {r['heldout_views']:>5}  "
              f"{r['heldout_psnr_raw']:>8.2f} {r['heldout_psnr_reproject']:>7.2f} "
              f"{r['heldout_psnr_fixed']:>7.2f} "
              f"{r['heldout_psnr_fixed'] - r['heldout_psnr_raw']:>+6.2f}   "
              f"{r['heldout_ssim_raw']:>8.3f} {r['heldout_ssim_fixed']:>6.3f}  {orc}"
              + (f"  ({r['note']})" if r.get("note") else ""))
    return rc


def cmd_fixer_pairs(a) -> int:
    from pydantic import ValidationError

    from freescale_core.errors import FreeScaleError
    from freescale_core.eval.fixer_pairs import make_scene_pairs
    from schemas.fixer_pairs import PairsConfig

    try:
        cfg = PairsConfig.model_validate(_parse_set(a.set))
    except ValidationError as e:
        print(f"error: --set: {e.errors()[0]['loc']}: {e.errors()[0]['msg']}", file=sys.stderr)
        return 2
    failed = []
    for path in a.scenes:
        p = Path(path)
        if not p.is_dir():
            print(f"error: scene folder {path} does not exist", file=sys.stderr)
            failed.append(path)
            continue
        try:
            for row in make_scene_pairs(p, a.out, cfg, seed=a.seed, force=a.force,
                                        log=lambda s: print(s, flush=True)):
                pass
        except FreeScaleError as e:
            print(f"error: {e}", file=sys.stderr)
            failed.append(path)
    if failed:
        print(f"{len(failed)} scene(s) failed: {' '.join(failed)}", file=sys.stderr)
        return 1
    return 0


def add_train_fixer_parser(sub) -> None:
    """``freescale train-fixer PAIRS OUT``: the train-fixer flow (flows/train_fixer.py)."""
    s = sub.add_parser("train-fixer", help="train the fixer network across scenes from "
                       "engine-made pairs, scenes held out by name, resumable")
    s.add_argument("pairs", help="pairs folder (<scene>/<fold>/ folders with done.json)")
    s.add_argument("out", help="run folder: fixer.pt, ckpt/last.pt, loss.jsonl, metrics.json, "
                   "loss.png, contact.png")
    s.add_argument("--holdout", nargs="+", default=[], metavar="SCENE",
                   help="scene ids never trained on (scored at the end)")
    s.add_argument("--train", nargs="+", default=None, metavar="SCENE",
                   help="train on these scenes only (None: every scene not held out)")
    s.add_argument("--steps", type=int, default=None, help="optimiser steps (None: steps)")
    s.add_argument("--cpu-seconds", type=float, default=None,
                   help="stop once the run used this many CPU seconds (max_cpu_seconds)")
    s.add_argument("--seed", type=int, default=None, help="model init and patch draws "
                   "(None: seed, 0)")
    s.add_argument("--init", default=None, metavar="FIXER_PT",
                   help="start from this fixer's weights (init_from): per-scene fine-tuning "
                        "with --train SCENE")
    s.add_argument("--resume", action="store_true",
                   help="continue the run in OUT from its last checkpoint")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a FixerTrainConfig field (schemas/fixer.py), e.g. "
                        "--set batch_size=4 --set model.base_channels=24")
    s.set_defaults(fn=cmd_train_fixer)


def cmd_train_fixer(a) -> int:
    from pydantic import ValidationError

    from schemas.fixer import FixerTrainConfig

    over = _parse_set(a.set)
    for key, v in (("steps", a.steps), ("seed", a.seed), ("max_cpu_seconds", a.cpu_seconds),
                   ("init_from", a.init)):
        if v is not None:
            over[key] = v
    try:
        cfg = FixerTrainConfig.model_validate(over)
    except ValidationError as e:
        err = e.errors()[0]
        print(f"error: invalid train-fixer setting {'.'.join(map(str, err['loc']))}: "
              f"{err['msg']}", file=sys.stderr)
        return 2
    from freescale_core.fixer.data import pair_folders
    from freescale_core.fixer.train import CKPT_NAME, FIXER_NAME

    if not Path(a.pairs).is_dir() or not pair_folders(a.pairs):
        print(f"error: no fixer pairs under {a.pairs} (expected <scene>/<fold>/done.json)",
              file=sys.stderr)
        return 2
    out = Path(a.out)
    if ((out / "ckpt" / CKPT_NAME).is_file() or (out / FIXER_NAME).is_file()) and not a.resume:
        print(f"error: {out} already holds a fixer run; add --resume to continue it, or pick "
              "another OUT", file=sys.stderr)
        return 2
    from flows.train_fixer import train_fixer_flow
    from freescale_core.fixer.train import ResumeMismatchError, RunExistsError

    try:
        m = train_fixer_flow(pairs=a.pairs, out=str(out), config=cfg, holdout=a.holdout,
                             train_scenes=a.train, resume=a.resume)
    except (RunExistsError, ResumeMismatchError, FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({k: m[k] for k in (
        "out", "checkpoint", "steps", "resumed_from", "stopped_by", "train_scenes",
        "holdout_scenes", "data_hash", "final_loss", "eval_on", "eval_psnr_render",
        "eval_psnr_fixed", "eval_ssim_render", "eval_ssim_fixed", "cpu_seconds")}))
    return 0
