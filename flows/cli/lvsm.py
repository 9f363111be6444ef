"""``freescale train-lvsm SHARDS``: the train-lvsm flow (flows/train_lvsm.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from flows.cli.common import _parse_set


def add_parsers(sub) -> None:
    """``freescale train-lvsm SHARDS``: the train-lvsm flow (flows/train_lvsm.py)."""
    s = sub.add_parser("train-lvsm", help="train the LVSM view-synthesis model from packed "
                       "shards (freescale shards pack), held-out loss / PSNR, checkpoints")
    s.add_argument("shards", help="shard folder written by freescale shards pack")
    s.add_argument("--out", default=None,
                   help="run folder: ckpt/last.pt, history.json, loss.png, metrics.json "
                        "(None: <SHARDS>-lvsm/seed<SEED>)")
    s.add_argument("--steps", type=int, default=None, help="optimiser steps (None: train.steps)")
    s.add_argument("--seed", type=int, default=0, help="model init and example draws")
    s.add_argument("--no-free-views", action="store_true",
                   help="captured views only (the baseline): train.sampler.use_free_views=false")
    s.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a TrainLVSMShardsConfig field (schemas/lvsm.py), e.g. "
                        "--set train.batch_size=4 --set heldout_scenes='[\"scene_0008\"]'")
    s.set_defaults(fn=cmd_train_lvsm)


def cmd_train_lvsm(a) -> int:
    from pydantic import ValidationError

    from freescale_core.downstream.lvsm.from_shards import RunExistsError
    from freescale_core.errors import StoreError
    from schemas.lvsm import TrainLVSMShardsConfig

    over = _parse_set(a.set)
    if a.steps is not None:
        over.setdefault("train", {})["steps"] = a.steps
    if a.no_free_views:
        over.setdefault("train", {}).setdefault("sampler", {})["use_free_views"] = False
    try:
        cfg = TrainLVSMShardsConfig.model_validate(over)
    except ValidationError as e:
        print(f"error: invalid --set: {e}", file=sys.stderr)
        return 2
    from freescale_core.store.shards import read_manifest

    try:
        read_manifest(a.shards)
    except FileNotFoundError:  # a damaged one is named by the check below
        print(f"error: no shard manifest at {str(a.shards).rstrip('/')}/manifest.parquet (make "
              "one with `freescale shards pack STORE SHARDS`)", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - unreachable bucket, credentials, damaged file
        from freescale_core.store.objstore import is_url

        if is_url(a.shards):
            print(f"error: cannot read the shard manifest at {str(a.shards).rstrip('/')}/"
                  f"manifest.parquet ({type(e).__name__}: {str(e).splitlines()[0][:200]})",
                  file=sys.stderr)
            return 2
    err = _shards_preflight(a.shards)
    if err:  # before Prefect starts: a damaged shard is one line, not a task traceback
        print(f"error: {err}", file=sys.stderr)
        return 2
    from flows.train_lvsm import default_out, train_lvsm_flow

    try:
        out = a.out or default_out(a.shards, a.seed)
    except ValueError as e:  # shards at a URL: no folder beside them
        print(f"error: {e}", file=sys.stderr)
        return 2
    from freescale_core.downstream.lvsm.train import CKPT_NAME

    if (Path(out) / "ckpt" / CKPT_NAME).is_file() and not a.resume:  # before Prefect starts
        print(f"error: {out} already holds a run; add --resume to continue it, or pick "
              "another --out", file=sys.stderr)
        return 2
    err = _resume_preflight(out, a.shards) if a.resume else None
    if err:  # before Prefect starts: resuming on other shards is one line, not a traceback
        print(f"error: {err}", file=sys.stderr)
        return 2
    try:
        m = train_lvsm_flow(shards=a.shards, out=out, seed=a.seed, config=cfg, resume=a.resume)
    except (RunExistsError, StoreError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({k: m[k] for k in (
        "out", "steps", "resumed_from", "final_train_loss", "final_train_psnr", "heldout_loss",
        "heldout_psnr", "best_heldout_psnr", "best_heldout_step", "it_s", "wall_seconds")}))
    return 0


def _resume_preflight(out: str, shards: str) -> str | None:
    """The shards folder and manifest the run in ``out`` started on (its ``split.json``)
    against ``shards``; None when they match or there is no run (the task checks the split)."""

    try:
        prev = json.loads((Path(out) / "split.json").read_text())
    except (OSError, ValueError):
        return None
    from freescale_core.store.shards import manifest_sha256, shards_location

    now, diffs = shards_location(shards), []
    if prev.get("shards") and shards_location(prev["shards"]) != now:
        diffs.append(f"shards {prev['shards']} -> {now}")
    sha = manifest_sha256(shards)
    if prev.get("manifest_sha256") and prev["manifest_sha256"] != sha:
        diffs.append("the shard manifest changed since the run started")
    return (f"cannot resume {out} on other data: {'; '.join(diffs)}; resume with the same "
            "shards and split, or start a new run in another folder") if diffs else None


def _shards_preflight(shards: str) -> str | None:
    """Every shard of ``shards`` against its manifest SHA-256 (once per process: the flow's
    reader, in this process, does not hash them again). None when all match."""
    from freescale_core.errors import StoreError
    from freescale_core.store.dataset import check_shard
    from freescale_core.store.objstore import is_url, local_of
    from freescale_core.store.shards import read_manifest

    if is_url(shards):  # the URL reader checks every shard it fetches against its SHA-256
        return None
    shards = local_of(shards)
    man = Path(shards) / "manifest.parquet"
    try:
        rows = read_manifest(shards).to_pylist()
    except Exception as e:  # noqa: BLE001 - a damaged manifest, named
        return f"shard manifest {man} cannot be read ({type(e).__name__}: {e})"
    seen = set()
    for r in rows:
        key = (r["shard_path"], r.get("shard_sha256"))
        if key in seen or not r.get("shard_sha256"):
            continue
        seen.add(key)
        try:
            check_shard(Path(shards) / r["shard_path"], r["shard_sha256"], man)
        except (StoreError, OSError) as e:
            return str(e)
    return None
