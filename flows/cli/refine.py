"""``freescale refine STORE``: the refine-3dgs flow (flows/refine_3dgs.py)."""

from __future__ import annotations

import sys
from pathlib import Path

from flows.cli.common import _one_line_validation, _parse_set


def add_parsers(sub) -> None:
    """``freescale refine STORE``: the refine-3dgs flow (flows/refine_3dgs.py)."""
    s = sub.add_parser("refine", help="per-scene 3DGS with free views as pseudo ground truth, "
                       "vs the baseline on held-out views (store made with recon_split=ood)")
    s.add_argument("store")
    s.add_argument("--scenes", nargs="+", default=None, help="scene ids (None: every scene with status ok)")
    s.add_argument("--arms", nargs="+", default=None,
                   help="arms among baseline baseline+time wiou random raw fixed fixed+conf "
                   "progressive oracle (docs/REFINE.md), optionally arm@rule "
                   "(rule: paper, reference, constant); None: baseline wiou")
    s.add_argument("--seeds", nargs="+", type=int, default=None, help="None: seed 0")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a RefineConfig field (schemas/refine.py), e.g. --set recon.max_iterations=900")
    s.set_defaults(fn=cmd_refine)


def cmd_refine(a) -> int:
    from flows.refine_3dgs import refine_3dgs
    from schemas.refine import RefineConfig

    over = _parse_set(a.set)
    if a.arms:
        over["arms"] = a.arms
    if a.seeds:
        over["seeds"] = a.seeds
    if "recon" in over:  # overrides start from the refine budget, not the paper's
        from schemas.refine import refine_recon_config

        r = over["recon"]
        if "max_iterations" in r:  # a fixed budget: every arm runs exactly these steps
            r.setdefault("min_iterations", r["max_iterations"])
        over["recon"] = {**refine_recon_config().model_dump(mode="json"), **r}
    try:
        cfg = RefineConfig.model_validate(over)
    except ValueError as e:  # pydantic ValidationError: a bad arm, --set key or value
        print(f"error: invalid refine setting: {_one_line_validation(e)}", file=sys.stderr)
        return 2
    err = _refine_preflight(a.store, a.scenes, cfg)
    if err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    refine_3dgs(store=a.store, scenes=a.scenes, config=cfg)
    return 0


def _refine_preflight(store: str, scenes: list[str] | None, cfg) -> str | None:
    """Everything ``refine`` can check before the flow starts (no Prefect server, no
    traceback): the store, the scenes, their held-out views, the seeds. None when fine."""
    import pyarrow.parquet as pq

    from freescale_core.errors import StoreError
    from freescale_core.store.reader import open_scenes

    bad = [s for s in cfg.seeds if s < 0]
    if bad:
        return f"refine seeds must be >= 0, got {bad}"
    if "://" in store:
        return (f"refine reads a local store; {store} is a URL (copy the scenes you refine to "
                "a local folder)")
    if not (Path(store) / "scenes").is_dir():
        return f"no store at {store} (no scenes/ folder)"
    try:
        sets = open_scenes(store, scenes)
    except StoreError as e:
        return str(e)
    if not sets:
        return f"no published (status ok) scene in {store} to refine"
    for fvs in sets:
        p = fvs.version_dir / "views.parquet"
        try:
            disp = pq.read_table(p, columns=["disposition"]).column("disposition").to_pylist()
        except Exception as e:  # noqa: BLE001 - a damaged table, named
            return f"scene {fvs.scene_id!r}: {p} cannot be read ({type(e).__name__}: {e})"
        if "heldout" not in disp:
            return (f"scene {fvs.scene_id!r}: {p} has no held-out views; publish the scene "
                    "with --set recon_split=ood to refine it")
    return None
