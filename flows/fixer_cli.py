"""``freescale fixer ...``: the fixer's training pairs and its scores (docs/FIXER.md)."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def add_fixer_parser(sub) -> None:
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


def add_score_parser(fx) -> None:  # filled in by the score command
    pass


def cmd_fixer_pairs(a) -> int:
    from pydantic import ValidationError

    from flows.cli import _parse_set
    from freescale_core.errors import FreeScaleError
    from freescale_core.fixer.pairs import make_scene_pairs
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
