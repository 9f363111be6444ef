"""``freescale scenes ls|show STORE``: browse the scenes of a store."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from flows.cli.common import _console, _fmt


def add_parsers(sub) -> None:
    sh = sub.add_parser("scenes", help="browse the scenes of a store").add_subparsers(dest="sub", required=True)
    s = sh.add_parser("ls", help="one line per scene")
    s.add_argument("store")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_scenes_ls)
    s = sh.add_parser("show", help="per-view table of one scene")
    s.add_argument("store")
    s.add_argument("scene")
    s.add_argument("--all", action="store_true", help="include infeasible/suppressed candidates")
    s.add_argument("--limit", type=int, default=60, help="rows to print")
    s.add_argument("--json", action="store_true", help="one JSON object per row")
    s.add_argument("--config", action="store_true",
                   help="print the resolved config the scene's version was made with")
    s.set_defaults(fn=cmd_scenes_show)


# Beyond this many scenes ``scenes ls`` prints plain aligned rows: a drawn table of 10,000
# rows took ~15 s here, and nobody reads it boxed.
TABLE_MAX_ROWS = 500


def _print_manifest(store) -> None:
    from freescale_core.store.store import MANIFEST_VIEW

    rows = store.manifest().to_pylist()
    cols = [c for c in MANIFEST_VIEW if any(c in r for r in rows)] or ["scene_id", "status"]
    if len(rows) > TABLE_MAX_ROWS:
        print(f"{store}/manifest.parquet ({len(rows)} scenes)")
        cells = [cols] + [[_plain(r.get(c)) for c in cols] for r in rows]
        width = [max(len(row[i]) for row in cells) for i in range(len(cols))]
        out = sys.stdout
        for row in cells:
            out.write("  ".join(v.ljust(w) for v, w in zip(row, width)).rstrip() + "\n")
    else:
        from rich.markup import escape
        from rich.table import Table

        t = Table(title=escape(f"{store}/manifest.parquet ({len(rows)} scenes)"))
        for c in cols:
            t.add_column(c, overflow="fold", max_width=60 if c == "error" else None)
        for r in rows:
            t.add_row(*[_fmt(r.get(c)) for c in cols])
        _console().print(t)
    for r in rows:  # ok but empty: say so, with the stage that removed every candidate
        if r.get("status") == "ok" and r.get("empty_reason"):
            print(f"warning: {r['scene_id']}: {r['empty_reason']}", file=sys.stderr)


def _plain(v) -> str:
    """A plain cell, formatted as the drawn table formats it."""
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v).replace("\n", " ")


def cmd_scenes_ls(a) -> int:
    from freescale_core.store.store import Store

    st = Store(a.store)
    if not st.scene_ids():
        print(f"error: no scenes in {a.store} (no scenes/*/status.json)", file=sys.stderr)
        return 2
    if a.json:
        for r in st.manifest().to_pylist():
            print(json.dumps(r, default=str))
        return 0
    _print_manifest(st)
    return 0


def cmd_scenes_show(a) -> int:
    from rich.table import Table

    from freescale_core.errors import StoreError
    from freescale_core.store.store import Store

    st = Store(a.store)
    if getattr(a, "config", False):
        return _print_scene_config(st, a.scene)
    try:
        views = st.views(a.scene)
    except StoreError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    rows = views.drop_columns(["world_from_cam"]).to_pylist()
    if not a.all:
        rows = [r for r in rows if r.get("disposition") in ("train", "free_view")]
    if a.json:
        for r in rows:
            print(json.dumps(r, default=str))
        return 0
    status = st.read_status(a.scene)
    t = Table(title=_fmt(f"{a.scene}: {len(rows)} of {views.num_rows} views "
                    f"({'all' if a.all else 'train + free views; --all for every candidate'}) "
                    f"status={status.get('status')}"))
    cols = [c for c in ["view_id", "kind", "mode", "disposition", "name", "score_f", "brisque",
                        "black_ratio", "depth_validity", "rect_steps", "reference_view",
                        "pred_psnr", "gt_psnr", "width", "height"] if c in views.column_names]
    for c in cols:
        t.add_column(c)
    for r in rows[: a.limit]:
        t.add_row(*[_fmt(r.get(c)) for c in cols])
    _console().print(t)
    if len(rows) > a.limit:
        print(f"... {len(rows) - a.limit} more rows (--limit)")
    d = st.current_version_dir(a.scene)
    print(f"files: {d}")
    return 0


def _print_scene_config(st, scene: str) -> int:
    """The resolved config the scene's current version was made with."""
    d = st.current_version_dir(scene)
    p = d / "config.json" if d is not None else None
    if p is None or not p.is_file():
        rc = Path(st.root) / "run_config.json"
        where = f"; the store's run config: {rc}" if rc.is_file() else ""
        print(f"error: no config.json for scene {scene!r} in {st.root} (not published, or "
              f"published before configs were stored){where}", file=sys.stderr)
        return 2
    rec = json.loads(p.read_text())
    # {"config_hash", "config"} (versions published since the dataset reader), or the bare config
    print(json.dumps(rec.get("config", rec) if isinstance(rec, dict) else rec, indent=2))
    return 0
