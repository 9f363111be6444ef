"""``freescale shards pack|ls|verify``: training shards packed from a store."""

from __future__ import annotations

import json
import sys

from flows.cli.common import _console, _fmt


def add_parsers(sub) -> None:
    sh = sub.add_parser("shards", help="training shards packed from a store").add_subparsers(
        dest="sub", required=True)
    s = sh.add_parser("pack", help="pack scenes of a store into training shards (incremental)")
    s.add_argument("store")
    s.add_argument("out")
    s.add_argument("--scenes", nargs="+", default=None, help="scene ids (default: every ok scene)")
    s.add_argument("--resolution", type=int, default=256,
                   help="square image side: resize the shorter side to this, centre-crop")
    s.add_argument("--views-per-shard", type=int, default=1024,
                   help="shard capacity in views (whole scenes per shard)")
    s.set_defaults(fn=cmd_shards_pack)
    s = sh.add_parser("ls", help="one line per (shard, scene) of a shard manifest")
    s.add_argument("out")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_shards_ls)
    s = sh.add_parser("verify", help="recompute every shard's SHA-256 against the manifest "
                                     "(exit 1 naming each damaged shard)")
    s.add_argument("out")
    s.set_defaults(fn=cmd_shards_verify)


def cmd_shards_pack(a) -> int:
    from freescale_core.errors import StoreError
    from freescale_core.store.shards import pack

    try:
        res = pack(a.store, a.out, scenes=a.scenes or None, resolution=a.resolution,
                   views_per_shard=a.views_per_shard)
    except (StoreError, ValueError) as e:
        _quiet_abandoned_zarr_tasks()
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(res.summary())
    return 0


def _quiet_abandoned_zarr_tasks() -> None:
    """After a failed zarr write (a full disk), zarr's event loop still holds the chunk
    writes it started; at exit asyncio reports each ('Task was destroyed but it is pending!',
    'Event loop is closed' tracebacks): the error line above already said what happened."""
    import logging
    import warnings

    logging.getLogger("asyncio").setLevel(logging.CRITICAL)
    warnings.filterwarnings("ignore", message="coroutine .* was never awaited",
                            category=RuntimeWarning)
    previous = sys.unraisablehook

    def hook(u) -> None:  # the abandoned writes' coroutines, finalised after the loop closed
        if isinstance(u.exc_value, RuntimeError) and "Event loop is closed" in str(u.exc_value):
            return
        previous(u)

    sys.unraisablehook = hook


def cmd_shards_verify(a) -> int:
    from freescale_core.store.shards import read_manifest, verify

    try:
        rows = read_manifest(a.out).to_pylist()
        bad = verify(a.out)
    except (FileNotFoundError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    shards = sorted({r["shard_path"] for r in rows})
    out = str(a.out).rstrip("/")  # a folder or a URL (s3://bucket/shards)
    for b in bad:
        path = next(r["shard_path"] for r in rows if r["shard"] == b)
        print(f"error: shard {out}/{path} does not match its SHA-256 in "
              f"{out}/manifest.parquet", file=sys.stderr)
    print(f"{a.out}: {len(shards) - len(bad)} of {len(shards)} shard(s) match the manifest")
    return 1 if bad else 0


def cmd_shards_ls(a) -> int:
    from rich.table import Table

    from freescale_core.store.shards import read_manifest

    try:
        rows = read_manifest(a.out).to_pylist()
    except FileNotFoundError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        for r in rows:
            print(json.dumps(r, default=str))
        return 0
    t = Table(title=f"{a.out}/manifest.parquet ({len({r['shard'] for r in rows})} shards, "
                    f"{len(rows)} scenes)")
    cols = ["shard", "scene_id", "n_views", "n_train", "n_free", "n_edges", "resolution",
            "shard_views", "shard_bytes", "source_version", "config_hash", "scene_sha256"]
    for c in cols:
        t.add_column(c)
    for r in rows:
        t.add_row(*[_fmt(r.get(c))[:16] if c.endswith("sha256") else _fmt(r.get(c))
                    for c in cols])
    _console().print(t)
    return 0
