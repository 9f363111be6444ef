"""``freescale`` command line: sample scene, inspect, run, resume, browse, serve."""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


# --------------------------------------------------------------------------- helpers
def _console():
    from rich.console import Console

    con = Console()
    if not con.is_terminal and "COLUMNS" not in os.environ:
        # piped / logged output: rich would assume 80 columns and wrap every header
        con = Console(width=160)
    return con


def _parse_set(items: list[str]) -> dict:
    """``a.b.c=1`` strings -> nested dict; values parsed as JSON when possible."""
    out: dict = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"--set expects key=value, got {it!r}")
        k, v = it.split("=", 1)
        try:
            val = json.loads(v)
        except json.JSONDecodeError:
            val = v
        d = out
        parts = k.split(".")
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = val
    return out


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


# --------------------------------------------------------------------------- commands
def cmd_sample_scene(a) -> int:
    from freescale_core.scene.sample import write_sample_scene

    t0 = time.perf_counter()
    p = write_sample_scene(a.dir, n_views=a.views, width=a.width, height=a.height, seed=a.seed)
    print(f"sample scene written to {p} ({a.views} views, {a.width}x{a.height}) "
          f"in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_inspect(a) -> int:
    from freescale_core.errors import SceneError
    from freescale_core.scene.describe import inspect_scene

    try:
        info = inspect_scene(a.scene_dir)
    except SceneError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(info, indent=2, default=str))
        return 0
    from rich.table import Table

    t = Table(title=f"scene {info.get('scene_id', a.scene_dir)}", show_header=False)
    for k, v in info.items():
        t.add_row(k, json.dumps(v, default=str) if isinstance(v, (list, dict)) else _fmt(v))
    _console().print(t)
    return 0


def _progress_thread(store_root: str, scene_ids: list[str], stop: threading.Event):
    """Poll the store's status files and draw a progress bar (works for any task runner)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from freescale_core.store.store import Store

    st = Store(store_root)
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), transient=False) as prog:
        tid = prog.add_task("scenes", total=len(scene_ids))
        while not stop.is_set():
            done, stages = 0, []
            for s in scene_ids:
                status = st.read_status(s)
                if status.get("status") in ("ok", "failed"):
                    done += 1
                elif status.get("status") == "running":
                    stages.append(f"{s}:{status.get('stage', '?')}")
            prog.update(tid, completed=done,
                        description=f"scenes ({', '.join(stages[:3]) or 'waiting'})")
            stop.wait(0.5)
        prog.update(tid, completed=sum(st.read_status(s).get("status") in ("ok", "failed")
                                       for s in scene_ids), description="scenes")


def run_flow(scenes: list[str], store: str, preset: str, overrides: dict, scale_out: str,
             workers: int, dask_address: str | None, force: bool, progress: bool = True) -> int:
    from flows.generate_dataset import expand_scenes, generate_dataset, scene_ids_for

    from freescale_core.store.store import Store, write_json_atomic

    Path(store).mkdir(parents=True, exist_ok=True)
    # Remember how the store was made, so `freescale resume STORE` needs nothing else.
    write_json_atomic(Path(store) / "run_config.json",
                      {"scenes": [str(s) for s in scenes], "preset": preset,
                       "overrides": overrides, "scale_out": scale_out, "workers": workers,
                       "dask_address": dask_address})
    ids = scene_ids_for(expand_scenes(scenes))
    stop = threading.Event()
    th = None
    if progress and sys.stderr.isatty():
        th = threading.Thread(target=_progress_thread, args=(store, ids, stop), daemon=True)
        th.start()
    try:
        from schemas.pipeline import PipelineConfig

        cfg = PipelineConfig.from_preset(preset, overrides)
        state = generate_dataset(scenes=[str(s) for s in scenes], store=store, config=cfg,
                                 scale_out=scale_out,
                                 n_workers=workers, dask_address=dask_address, force=force,
                                 return_state=True)
    finally:
        stop.set()
        if th:
            th.join(timeout=5)
    _print_manifest(Store(store))
    if state.is_failed():
        print(f"\nrun failed: {state.message}", file=sys.stderr)
        print(f"fix the inputs, then: freescale resume {store}", file=sys.stderr)
        return 1
    print(f"\n{state.message}")
    return 0


def cmd_run(a) -> int:
    return run_flow(a.scenes, a.store, a.preset, _parse_set(a.set), a.scale_out, a.workers,
                    a.dask_address, a.force, progress=not a.no_progress)


def cmd_resume(a) -> int:
    cfg_path = Path(a.store) / "run_config.json"
    if not cfg_path.is_file():
        print(f"error: {cfg_path} not found: is {a.store} a FreeScale store?", file=sys.stderr)
        return 2
    rc = json.loads(cfg_path.read_text())
    return run_flow(rc["scenes"], a.store, rc["preset"], rc.get("overrides") or {},
                    a.scale_out or rc.get("scale_out", "threads"),
                    a.workers or rc.get("workers", 2), rc.get("dask_address"), False,
                    progress=not a.no_progress)


def _print_manifest(store) -> None:
    from rich.table import Table

    rows = store.manifest().to_pylist()
    t = Table(title=f"{store.root}/manifest.parquet ({len(rows)} scenes)")
    cols = ["scene_id", "status", "n_images", "n_gaussians", "n_candidates", "n_selected",
            "n_final", "seconds_total", "error"]
    cols = [c for c in cols if any(c in r for r in rows)] or ["scene_id", "status"]
    for c in cols:
        t.add_column(c, overflow="fold", max_width=60 if c == "error" else None)
    for r in rows:
        t.add_row(*[_fmt(r.get(c)) for c in cols])
    _console().print(t)


def cmd_shards_ls(a) -> int:
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


def cmd_shards_show(a) -> int:
    from rich.table import Table

    from freescale_core.errors import StoreError
    from freescale_core.store.store import Store

    st = Store(a.store)
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
    t = Table(title=f"{a.scene}: {len(rows)} of {views.num_rows} views "
                    f"({'all' if a.all else 'train + free views; --all for every candidate'}) "
                    f"status={status.get('status')}")
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


def cmd_serve(a) -> int:
    from flows.serve import main as serve_main

    return serve_main(port=a.port)


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    from schemas.pipeline import PRESETS

    p = argparse.ArgumentParser(prog="freescale", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("sample-scene", help="write the embedded procedural sample scene")
    s.add_argument("dir")
    s.add_argument("--views", type=int, default=36)
    s.add_argument("--width", type=int, default=256)
    s.add_argument("--height", type=int, default=192)
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(fn=cmd_sample_scene)

    s = sub.add_parser("inspect", help="describe a scene folder without processing it")
    s.add_argument("scene_dir")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_inspect)

    def add_run_opts(s):
        s.add_argument("--scale-out", choices=["threads", "dask"], default=None)
        s.add_argument("--workers", type=int, default=None, help="concurrent scenes")
        s.add_argument("--no-progress", action="store_true")

    s = sub.add_parser("run", help="run generate-dataset on scene folders (locally)")
    s.add_argument("scenes", nargs="+", help="scene folders or globs")
    s.add_argument("--store", required=True)
    s.add_argument("--preset", choices=sorted(PRESETS), default="paper")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a config field, e.g. --set select.nms.max_views=200")
    s.add_argument("--dask-address", default=None)
    s.add_argument("--force", action="store_true", help="re-run scenes that are already ok")
    add_run_opts(s)
    s.set_defaults(fn=lambda a: cmd_run(_defaults(a)))

    s = sub.add_parser("resume", help="re-run only failed or unfinished scenes of a store")
    s.add_argument("store")
    add_run_opts(s)
    s.set_defaults(fn=cmd_resume)

    sh = sub.add_parser("shards", help="browse a store").add_subparsers(dest="sub", required=True)
    s = sh.add_parser("ls", help="one line per scene")
    s.add_argument("store")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_shards_ls)
    s = sh.add_parser("show", help="per-view table of one scene")
    s.add_argument("store")
    s.add_argument("scene")
    s.add_argument("--all", action="store_true", help="include infeasible/suppressed candidates")
    s.add_argument("--limit", type=int, default=60)
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_shards_show)

    s = sub.add_parser("serve", help="start a local Prefect server and serve the deployments")
    s.add_argument("--port", type=int, default=int(os.environ.get("PREFECT_PORT", 4200)))
    s.set_defaults(fn=cmd_serve)
    return p


def _defaults(a):
    a.scale_out = a.scale_out or "threads"
    a.workers = a.workers or 2
    return a


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    try:
        return int(a.fn(a) or 0)
    except BrokenPipeError:  # `freescale shards show ... | head`: the reader left
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
