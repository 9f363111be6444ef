"""``freescale`` command line: sample scene, inspect, run, resume, browse scenes, training
shards, export, config, report, the downstream flows (refine, train-lvsm), serve."""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
# the temporary API server of a local run starts slowly on a loaded 2-core machine
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")


# --------------------------------------------------------------------------- helpers
def _console():
    from rich.console import Console

    con = Console()
    if not con.is_terminal and "COLUMNS" not in os.environ:
        # piped / logged output: rich would assume 80 columns and wrap every header; a table
        # takes only the width it needs, so a wide limit costs nothing (the manifest view has
        # a dozen columns: at 160 its headers were cut to "scene_…")
        con = Console(width=400)
    return con


from flows.setargs import parse_set as _parse_set  # noqa: E402


def _fmt(v) -> str:
    """A table cell as rich markup: values are escaped (an error ending in ``[/a/path]`` is
    text, not a closing markup tag)."""
    from rich.markup import escape

    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return escape(str(v))


# --------------------------------------------------------------------------- commands
def cmd_sample_scene(a) -> int:
    from freescale_core.scene.sample import write_sample_scene

    t0 = time.perf_counter()
    try:
        p = write_sample_scene(a.dir, n_views=a.views, width=a.width, height=a.height,
                               seed=a.seed)
    except ValueError as e:  # e.g. --views 1: "n_views must be >= 2"
        print(f"error: sample scene {a.dir}: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: sample scene {a.dir} cannot be written: {e.strerror or e}"
              f"{f' ({e.filename})' if getattr(e, 'filename', None) else ''}", file=sys.stderr)
        return 2
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

    from rich.markup import escape

    t = Table(title=escape(f"scene {info.get('scene_id', a.scene_dir)}"), show_header=False)
    for k, v in info.items():
        t.add_row(_fmt(k), _fmt(json.dumps(v, default=str)) if isinstance(v, (list, dict)) else _fmt(v))
    _console().print(t)
    return 0


def _check_scenes(scenes: list[str]) -> tuple[list[Path], list[str]]:
    """Expand each argument alone: ``(absolute scene folders, one-line errors)``. A path
    that does not exist (or a glob matching nothing) is an error for that argument only."""
    from flows.generate_dataset import expand_scenes

    found: list[Path] = []
    errors: list[str] = []
    for s in scenes:
        try:
            for p in expand_scenes([s]):
                if p not in found:
                    found.append(p)
        except (FileNotFoundError, OSError) as e:
            errors.append(str(e.args[0] if e.args else e))
    return found, errors


def _interrupted(store: str, ids: list[str], why: str) -> None:
    """Mark this run's unfinished scenes failed (not left 'running') after an interrupt."""
    from freescale_core.store.store import Store

    st = Store(store)
    for sid in ids:
        s = st.read_status(sid)
        if s.get("status") in ("running", "pending"):
            st.update_status(sid, status="failed", error_type="Interrupted",
                             error=f"[{s.get('stage', '?')}] scene '{sid}': interrupted "
                                   f"({why}); run `freescale resume {store}`")


def run_flow(scenes: list[str], store: str, preset: str, overrides: dict, scale_out: str,
             workers: int, dask_address: str | None, force: bool, progress: bool = True,
             config: dict | None = None) -> int:
    """Validate everything first (config, scene paths), then run the flow locally.

    ``config`` (a complete config dump, from ``run_config.json``) takes the place of
    ``preset``; ``overrides`` apply on top of either. Nothing is written and no Prefect server
    starts when the config is invalid or no scene path exists. A missing path among several
    is reported on one line and left out (not remembered for ``resume``); the others run; the
    exit code is then 1. The flow records ``run_config.json`` for ``resume``.
    """
    import contextlib
    import signal

    from flows.generate_dataset import assign_scene_ids, generate_dataset
    from flows.progress_view import FIRST_RUN_NOTE, ProgressView, numba_cache_cold

    from freescale_core.store.store import Store
    from schemas.pipeline import PipelineConfig, _deep_merge

    try:
        if config is not None:
            cfg = PipelineConfig.model_validate(_deep_merge(config, overrides))
        else:
            cfg = PipelineConfig.from_preset(preset, overrides)
    except ValueError as e:  # pydantic ValidationError: a bad --set
        print(f"error: invalid config: {e}", file=sys.stderr)
        return 2
    if cfg.select.grid.resolution != "auto":  # refuse a grid that cannot fit, up front
        from freescale_core.errors import ResourceLimitError
        from freescale_core.select.certainty import check_grid_memory

        try:
            check_grid_memory(int(cfg.select.grid.resolution), 0, cfg.select.grid, "every scene")
        except ResourceLimitError as e:
            print(f"error: {e}", file=sys.stderr)
            return 2
    paths, bad = _check_scenes(scenes)
    for b in bad:
        print(f"error: {b} (skipped)", file=sys.stderr)
    if not paths:
        print("error: no scene folder to run; nothing was written", file=sys.stderr)
        return 2
    if "://" not in store:  # an object-store URL needs no folder
        Path(store).mkdir(parents=True, exist_ok=True)
    try:
        ids = assign_scene_ids(paths, Store(store))[0]
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    how = f"{preset} -> {cfg.preset}" if preset == "auto" else cfg.preset
    print(f"freescale {_version()}: {len(ids)} scene(s) -> {store}, preset {how}"
          + (f", {len(overrides)} override(s)" if overrides else "")
          + f" (`freescale config show --preset {cfg.preset}` prints every field)",
          file=sys.stderr, flush=True)
    if numba_cache_cold():
        print(FIRST_RUN_NOTE, file=sys.stderr, flush=True)
    view = ProgressView(store, ids) if progress else contextlib.nullcontext()

    def on_term(signum, frame):
        # SIGTERM: Prefect's flow engine turns it into an exception whose unwinding waits
        # for the running stage threads (minutes). It then re-sends the signal to this
        # handler: mark the run's unfinished scenes failed and leave right here (stage
        # outputs are atomic), after the exit handlers (they stop the temporary server).
        _leave_interrupted(store, ids, f"signal {signum}")

    try:  # pycolmap's logging library installs a C-level SIGTERM handler when imported
        import pycolmap  # noqa: F401  (import it first, so that ours replaces it)
    except ImportError:
        pass
    prev = signal.signal(signal.SIGTERM, on_term) \
        if threading.current_thread() is threading.main_thread() else None
    engine, prefect_handler = None, None
    if prev is not None:
        try:  # Prefect swaps in its own SIGTERM handler for the flow run: ours instead
            import prefect.utilities.engine as engine

            prefect_handler = engine._prefect_sigterm_handler
            engine._prefect_sigterm_handler = on_term
        except (ImportError, AttributeError):
            engine = None
    try:
        with view:
            state = generate_dataset(scenes=[str(p) for p in paths], store=store, config=cfg,
                                     scale_out=scale_out, n_workers=workers,
                                     dask_address=dask_address, force=force, return_state=True)
    except (KeyboardInterrupt, _termination_signal()) as e:
        if prev is not None:
            _leave_interrupted(store, ids, str(e) or type(e).__name__)
        _interrupted(store, ids, str(e) or type(e).__name__)
        return 130
    finally:
        if prev is not None:
            signal.signal(signal.SIGTERM, prev)
        if engine is not None and prefect_handler is not None:
            engine._prefect_sigterm_handler = prefect_handler
    _print_manifest(Store(store))
    if state.is_failed():
        print(f"\nrun failed: {state.message}", file=sys.stderr)
        print(f"fix the inputs, then: freescale resume {store}", file=sys.stderr)
        return 1
    print(f"\n{state.message}")
    if bad:
        print(f"{len(bad)} scene path(s) not found (listed above)", file=sys.stderr)
        return 1
    return 0


def _leave_interrupted(store: str, ids: list[str], why: str) -> None:
    """Mark the run's unfinished scenes failed, run the exit handlers (at most 20 s: they
    stop Prefect's temporary server) and exit 130 without joining stage threads (which would
    keep the process alive until the running stage finishes)."""
    import atexit

    try:
        _interrupted(store, ids, why)
        print(f"\ninterrupted ({why}): unfinished scenes marked failed; "
              f"freescale resume {store}", file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        t = threading.Thread(target=atexit._run_exitfuncs, daemon=True)
        t.start()
        t.join(timeout=20)
    finally:
        os._exit(130)


def _termination_signal() -> type[BaseException]:
    """Prefect's own SIGTERM exception (its flow engine swaps the handler during a run)."""
    try:
        from prefect.exceptions import TerminationSignal

        return TerminationSignal
    except ImportError:  # pragma: no cover - older Prefect
        return KeyboardInterrupt


def glob_magic(s: str) -> bool:
    import glob

    return glob.has_magic(str(s))


def cmd_run(a) -> int:
    return run_flow(a.scenes, a.store, a.preset, _parse_set(a.set), a.scale_out, a.workers,
                    a.dask_address, a.force, progress=not a.no_progress)


def cmd_resume(a) -> int:
    """Re-run the store's failed / unfinished scenes with the config it was made with (a
    store made by a deployment too: the flow writes ``run_config.json``); ``--set`` fixes a
    bad override (the changed config re-runs the scenes it affects)."""
    from freescale_core.store.store import read_store_file

    blob = read_store_file(a.store, "run_config.json")
    if blob is None:
        print(f"error: {a.store.rstrip('/')}/run_config.json not found: is {a.store} a "
              f"FreeScale store?", file=sys.stderr)
        return 2
    rc = json.loads(blob)
    overrides = _parse_set(getattr(a, "set", None))
    if rc.get("config") is not None:
        return run_flow(rc["scenes"], a.store, rc.get("preset", "paper"), overrides,
                        a.scale_out or rc.get("scale_out", "threads"),
                        a.workers or rc.get("workers", 2), rc.get("dask_address"), False,
                        progress=not a.no_progress, config=rc["config"])
    from schemas.pipeline import _deep_merge

    return run_flow(rc["scenes"], a.store, rc["preset"],
                    _deep_merge(rc.get("overrides") or {}, overrides),
                    a.scale_out or rc.get("scale_out", "threads"),
                    a.workers or rc.get("workers", 2), rc.get("dask_address"), False,
                    progress=not a.no_progress)


def _print_manifest(store) -> None:
    from rich.table import Table

    rows = store.manifest().to_pylist()
    from rich.markup import escape

    t = Table(title=escape(f"{store}/manifest.parquet ({len(rows)} scenes)"))
    from flows.generate_dataset import MANIFEST_VIEW

    cols = list(MANIFEST_VIEW)
    cols = [c for c in cols if any(c in r for r in rows)] or ["scene_id", "status"]
    for c in cols:
        t.add_column(c, overflow="fold", max_width=60 if c == "error" else None)
    for r in rows:
        t.add_row(*[_fmt(r.get(c)) for c in cols])
    _console().print(t)
    for r in rows:  # ok but empty: say so, with the stage that removed every candidate
        if r.get("status") == "ok" and r.get("empty_reason"):
            print(f"warning: {r['scene_id']}: {r['empty_reason']}", file=sys.stderr)


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


def cmd_export(a) -> int:
    from freescale_core.errors import StoreError
    from freescale_core.exports import export

    opts: dict = {"overwrite": a.overwrite}
    if a.format == "nerfstudio":
        opts.update(free_views=a.free_views, depth=a.depth)
    try:
        res = export(a.format, a.store, a.out, a.scenes or None, **opts)
    except (StoreError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a full disk, a read-only mount: nothing half-written is left
        print(f"error: export to {a.out} failed: {e.strerror or e}"
              f"{f' ({e.filename})' if getattr(e, 'filename', None) else ''}", file=sys.stderr)
        return 2
    print(res.summary())
    return 0


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
    for b in bad:
        path = next(r["shard_path"] for r in rows if r["shard"] == b)
        print(f"error: shard {Path(a.out) / path} does not match its SHA-256 in "
              f"{Path(a.out) / 'manifest.parquet'}", file=sys.stderr)
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


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("freescale")
    except Exception:  # noqa: BLE001 - not installed: the engine's own version
        from freescale_core import __version__

        return __version__


def cmd_config_show(a) -> int:
    from schemas.pipeline import PipelineConfig

    try:
        cfg = PipelineConfig.from_preset(a.preset, _parse_set(a.set))
    except ValueError as e:
        print(f"error: invalid config: {e}", file=sys.stderr)
        return 2
    d = cfg.model_dump(mode="json")
    if a.json:
        print(json.dumps(d, indent=2))
        return 0
    import yaml

    head = f"# preset {a.preset} -> {cfg.preset}" if a.preset == "auto" else f"# preset {cfg.preset}"
    print(head + (f", overrides {_parse_set(a.set)}" if a.set else ""))
    class _Dumper(yaml.SafeDumper):  # block mappings, short lists on one line
        pass

    _Dumper.add_representer(list, lambda dm, v: dm.represent_sequence(
        "tag:yaml.org,2002:seq", v, flow_style=True))
    print(yaml.dump(d, Dumper=_Dumper, sort_keys=False, width=100).rstrip())
    return 0


def cmd_config_fields(a) -> int:
    from flows.config_help import field_docs, one_line

    docs = field_docs()
    if a.json:
        for f in docs:
            print(json.dumps({"name": f.name, "type": f.type, "defaults": f.defaults,
                              "doc": f.doc}))
        return 0
    from rich.table import Table

    t = Table(title=f"{len(docs)} config fields (--set KEY=VALUE); docs/CONFIG.md")
    t.add_column("field", no_wrap=True)
    for c in ("type", "paper", "cpu", "fast"):
        t.add_column(c, overflow="fold", max_width=22)
    t.add_column("doc", overflow="fold", min_width=50)
    for f in docs:
        t.add_row(f.name, f.type, *[json.dumps(f.defaults[p]) for p in ("paper", "cpu", "fast")],
                  one_line(f.doc))
    _console().print(t)
    return 0


def cmd_report(a) -> int:
    from flows.report import write_report

    from freescale_core.store.store import Store

    st = Store(a.store)
    if not st.scene_ids():
        print(f"error: no scenes in {a.store} (no scenes/*/status.json)", file=sys.stderr)
        return 2
    remote = a.output is None and "://" in a.store  # written locally, then put beside it
    out = Path(a.output or (st.root if remote else Path(a.store)) / "report.html")
    t0 = time.perf_counter()
    problems: list[str] = []
    try:
        write_report(st, out, problems)
    except OSError as e:
        print(f"error: report {out} cannot be written: {e.strerror or e}", file=sys.stderr)
        return 2
    if remote:
        st.write_file("report.html", out.read_bytes())
        print(f"report put to {st.url}/report.html")
    print(f"report written to {out} ({out.stat().st_size / 1e6:.1f} MB, "
          f"{len(st.scene_ids())} scenes) in {time.perf_counter() - t0:.1f} s")
    for p in problems:  # the report shows them as 'unreadable', the healthy scenes in full
        print(f"error: {p}", file=sys.stderr)
    return 1 if problems else 0


def cmd_serve(a) -> int:
    from flows.serve import main as serve_main

    return serve_main(port=a.port)


# --------------------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    from flows.config_help import help_epilog
    from schemas.pipeline import PRESET_CHOICES

    p = argparse.ArgumentParser(prog="freescale", description=__doc__, formatter_class=_Fmt)
    p.add_argument("--version", action="version", version=f"freescale {_version()}")
    sub = p.add_subparsers(dest="cmd", required=True)
    _add = sub.add_parser

    def add_parser(name, **kw):  # every sub-command shows its defaults
        kw.setdefault("formatter_class", _Fmt)
        return _add(name, **kw)

    sub.add_parser = add_parser

    s = sub.add_parser("sample-scene", help="write the embedded procedural sample scene")
    s.add_argument("dir")
    s.add_argument("--views", type=int, default=36, help="captured views")
    s.add_argument("--width", type=int, default=256, help="image width (px)")
    s.add_argument("--height", type=int, default=192, help="image height (px)")
    s.add_argument("--seed", type=int, default=0, help="scene seed")
    s.set_defaults(fn=cmd_sample_scene)

    s = sub.add_parser("inspect", help="describe a scene folder without processing it")
    s.add_argument("scene_dir")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_inspect)

    def add_run_opts(s):
        s.add_argument("--scale-out", choices=["threads", "dask"], default=None,
                       help="task runner (None: threads, or the store's on resume)")
        s.add_argument("--workers", type=int, default=None,
                       help="concurrent scenes (None: 2, or the store's on resume)")
        s.add_argument("--no-progress", action="store_true",
                       help="no progress bars / lines")
        s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="override a config field, e.g. --set select.nms.max_views=200 "
                            "(every field: freescale config fields)")

    s = sub.add_parser("run", help="run generate-dataset on scene folders (locally)",
                       epilog=help_epilog("cpu"))
    s.add_argument("scenes", nargs="+", help="scene folders or globs")
    s.add_argument("--store", required=True, help="output store folder")
    s.add_argument("--preset", choices=PRESET_CHOICES, default="auto",
                   help="auto: paper where CUDA is present, cpu otherwise (printed at start); "
                        "paper: the paper's numbers (hours per scene on a CPU); cpu: paper "
                        "selection, <= 10 min reconstruction; fast: seconds, for demos")
    s.add_argument("--dask-address", default=None,
                   help="tcp://host:8786 of an existing Dask cluster (with --scale-out dask)")
    s.add_argument("--force", action="store_true", help="re-run scenes that are already ok")
    add_run_opts(s)
    s.set_defaults(fn=lambda a: cmd_run(_defaults(a)))

    s = sub.add_parser("resume", help="re-run only failed or unfinished scenes of a store")
    s.add_argument("store")
    add_run_opts(s)
    s.set_defaults(fn=cmd_resume)

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

    s = sub.add_parser("export", help="export scenes of a store to another tool's format")
    s.add_argument("format", choices=["nerfstudio", "lvsm", "gsplat", "colmap"])
    s.add_argument("store")
    s.add_argument("out")
    s.add_argument("--scenes", nargs="+", default=None, help="scene ids (default: every ok scene)")
    s.add_argument("--free-views", choices=["train", "val"], default="train",
                   help="nerfstudio: free views as extra training views or as val_filenames")
    s.add_argument("--depth", action="store_true", help="nerfstudio: write 16-bit depth PNGs")
    s.add_argument("--overwrite", action="store_true", help="replace an existing OUT")
    s.set_defaults(fn=cmd_export)

    cf = sub.add_parser("config", help="the pipeline config: resolved values, every field"
                        ).add_subparsers(dest="sub", required=True)
    s = cf.add_parser("show", help="print the resolved config of a preset + overrides",
                      formatter_class=_Fmt)
    s.add_argument("--preset", choices=PRESET_CHOICES, default="auto",
                   help="auto: paper with CUDA, cpu without")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field, as for run")
    s.add_argument("--json", action="store_true", help="JSON instead of YAML")
    s.set_defaults(fn=cmd_config_show)
    s = cf.add_parser("fields", help="every config field: type, default per preset, doc",
                      formatter_class=_Fmt)
    s.add_argument("--json", action="store_true", help="one JSON object per field")
    s.set_defaults(fn=cmd_config_fields)

    s = sub.add_parser("report", help="one self-contained HTML report of a store "
                       "(figures, a table per scene, failed scenes, a 3D camera view)")
    s.add_argument("store")
    s.add_argument("-o", "--output", default=None, help="HTML file (None: STORE/report.html)")
    s.set_defaults(fn=cmd_report)

    add_refine_parser(sub)
    add_train_lvsm_parser(sub)
    add_train_fixer_parser(sub)
    add_evaluate_parser(sub)
    from flows.fixer_cli import add_fixer_parser

    add_fixer_parser(sub)

    s = sub.add_parser("serve", help="start a local Prefect server and serve the deployments")
    s.add_argument("--port", type=int, default=int(os.environ.get("PREFECT_PORT", 4200)))
    s.set_defaults(fn=cmd_serve)
    return p


class _Fmt(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in every option's help; the epilog (the config fields) kept as written."""


def add_refine_parser(sub) -> None:
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


def _one_line_validation(e: Exception) -> str:
    """A pydantic ValidationError (or any ValueError) as one line: each error's field and
    message, joined by '; '."""
    errs = getattr(e, "errors", None)
    if callable(errs):
        try:
            return "; ".join(
                (f"{'.'.join(map(str, x['loc']))}: " if x["loc"] else "")
                + x["msg"].removeprefix("Value error, ")
                + (f" (got {x['input']!r})" if x.get("type") == "extra_forbidden" else "")
                for x in errs())
        except Exception:  # noqa: BLE001 - fall back on the message
            pass
    return " ".join(str(e).split())


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


def add_train_lvsm_parser(sub) -> None:
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
    if not (Path(a.shards) / "manifest.parquet").is_file():
        print(f"error: no shard manifest at {a.shards}/manifest.parquet (make one with "
              "`freescale shards pack STORE SHARDS`)", file=sys.stderr)
        return 2
    err = _shards_preflight(a.shards)
    if err:  # before Prefect starts: a damaged shard is one line, not a task traceback
        print(f"error: {err}", file=sys.stderr)
        return 2
    from flows.train_lvsm import default_out, train_lvsm_flow

    out = a.out or default_out(a.shards, a.seed)
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
    import hashlib

    try:
        prev = json.loads((Path(out) / "split.json").read_text())
    except (OSError, ValueError):
        return None
    now, diffs = str(Path(shards).absolute()), []
    if prev.get("shards") and str(Path(prev["shards"]).absolute()) != now:
        diffs.append(f"shards {prev['shards']} -> {now}")
    sha = hashlib.sha256((Path(shards) / "manifest.parquet").read_bytes()).hexdigest()
    if prev.get("manifest_sha256") and prev["manifest_sha256"] != sha:
        diffs.append("the shard manifest changed since the run started")
    return (f"cannot resume {out} on other data: {'; '.join(diffs)}; resume with the same "
            "shards and split, or start a new run in another folder") if diffs else None


def _shards_preflight(shards: str) -> str | None:
    """Every shard of ``shards`` against its manifest SHA-256 (once per process: the flow's
    reader, in this process, does not hash them again). None when all match."""
    from freescale_core.errors import StoreError
    from freescale_core.store.dataset import check_shard
    from freescale_core.store.shards import read_manifest

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


def add_evaluate_parser(sub) -> None:
    """``freescale evaluate SCENES``: the evaluate-engine flow (flows/evaluate_engine.py)."""
    s = sub.add_parser("evaluate", help="sweep knobs over scenes: seconds per scene vs accuracy, "
                       "a Pareto chart, sizing and stability tables (docs/EVALUATION.md)")
    s.add_argument("scenes", nargs="*", help="scene folders, proc:NAME (proc:sizes, "
                   "proc:failures), real:NAME or real:all, real:NAME@FAMILY (few<N>, dark, "
                   "rotnoise<deg>, transnoise<frac>; real:failures: all); --quick alone: "
                   "proc:tiny")
    s.add_argument("--out", default="data/eval", help="output folder (points are cached there)")
    s.add_argument("--preset", default=None, choices=["paper", "cpu", "fast"],
                   help="preset of the base point (default fast)")
    s.add_argument("--knob", action="append", default=[], metavar="NAME=V1,V2",
                   help="sweep a knob, e.g. --knob grid_r=32,64,adaptive (names: grid_r "
                   "candidates resolution gaussians steps seconds visibility reference rectifier "
                   "masks)")
    s.add_argument("--presets", nargs="*", default=None, help="presets as labelled points")
    s.add_argument("--preset-set", action="append", default=[], metavar="PRESET:KEY=VALUE",
                   help="override a field of a preset's labelled point, e.g. cpu:recon.max_seconds=60")
    s.add_argument("--sizing", nargs="*", default=None,
                   help="knobs compared adaptive vs half vs double (grid_r gaussians resolution "
                   "candidates steps)")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a PipelineConfig field of every point")
    s.add_argument("--real-knobs", choices=["all", "recon"], default=None,
                   help="on real scenes sweep all knobs or only those that change the "
                   "reconstruction (held-out PSNR)")
    s.add_argument("--true-psnr", type=float, default=None, help="dB for a free view to be true")
    s.add_argument("--eval-long-side", type=int, default=None, metavar="PX",
                   help="held-out PSNR/SSIM of every point at this long side per scene "
                   "(default 512; never upscaled)")
    s.add_argument("--downstream", nargs="*", default=None, choices=["refine"],
                   help="downstream gain per point: refine = 3DGS refinement with vs without "
                   "the free views (cached with the point)")
    s.add_argument("--refine-steps", type=int, default=None, help="refinement steps per arm "
                   "(default 150)")
    s.add_argument("--refine-seeds", nargs="+", type=int, default=None,
                   help="refinement seeds (default 0)")
    s.add_argument("--refine-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a RefineConfig field of the comparison, e.g. "
                   "recon.max_long_side=64")
    s.add_argument("--seeds", nargs="+", type=int, default=None,
                   help="run every point once per pipeline seed; means and spread are shown")
    s.add_argument("--quick", action="store_true", help="tiny scene, tiny budgets, two knob "
                   "values and the fast preset (minutes)")
    s.set_defaults(fn=cmd_evaluate)


def cmd_evaluate(a) -> int:
    from flows.evaluate_engine import evaluate_engine
    from freescale_core.eval.sweep import quick_config
    from schemas.evaluate import EvaluateConfig

    base = quick_config().model_dump() if a.quick else {}
    scenes = a.scenes or (["proc:tiny"] if a.quick else [])
    if not scenes:
        print("error: name at least one scene (or use --quick)", file=sys.stderr)
        return 2
    if a.preset:
        base["preset"] = a.preset
    if a.set:
        base["overrides"] = _deep_merge_dicts(base.get("overrides", {}), _parse_set(a.set))
    knobs = dict(base.get("knobs", {}))
    for k in a.knob:
        name, _, vals = k.partition("=")
        knobs[name.strip()] = [_knob_value(v) for v in vals.split(",") if v.strip()]
    base["knobs"] = knobs
    po = dict(base.get("preset_overrides", {}))
    for item in a.preset_set:
        preset, _, kv = item.partition(":")
        po[preset] = _deep_merge_dicts(po.get(preset, {}), _parse_set([kv]))
    base["preset_overrides"] = po
    # options given on the command line replace the (quick) defaults: argument -> field
    for arg, field in (("presets", "presets"), ("sizing", "sizing"),
                       ("true_psnr", "true_psnr_db"), ("real_knobs", "real_knobs"),
                       ("eval_long_side", "eval_long_side"), ("downstream", "downstream"),
                       ("refine_steps", "refine_steps"), ("refine_seeds", "refine_seeds"),
                       ("seeds", "seeds")):
        if getattr(a, arg) is not None:
            base[field] = getattr(a, arg)
    if a.refine_set:
        base["refine_overrides"] = _parse_set(a.refine_set)
    try:
        cfg = EvaluateConfig.model_validate(base)
    except ValueError as e:
        print(f"error: invalid evaluation config: {_one_line_validation(e)}", file=sys.stderr)
        return 2
    err = _evaluate_preflight(scenes, cfg)
    if err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    r = evaluate_engine(scenes=scenes, out=a.out, config=cfg)
    print(f"{r['n_points']} points ({len(r['computed'])} computed, {len(r['cached'])} cached)")
    for k, v in r["files"].items():
        print(f"  {k}: {v}")
    for s in r["skipped"]:
        print(f"  skipped: {s}")
    print(f"  tables: {Path(a.out) / 'tables.md'}")
    return 0


def _evaluate_preflight(scenes: list[str], cfg) -> str | None:
    """Everything ``evaluate`` can check before the flow starts (no Prefect server, no
    traceback): the scene names, the seeds, the presets of ``--preset-set``, a ``preset``
    given through ``--set``, and every point's config (knob names and values, ``--set``
    keys). None when fine."""
    from freescale_core.eval.real_variants import is_family
    from freescale_core.eval.scenes import _SPECS
    from freescale_core.eval.sweep import plan_points

    for s in scenes:
        if s.startswith("proc:"):
            name = s[5:]
            if name not in _SPECS and name not in ("sizes", "failures"):
                return (f"unknown evaluation scene {s!r}; expected proc: with one of "
                        f"{['sizes', 'failures', *_SPECS]}")
        elif s.startswith("real:"):
            _, _, family = s[5:].partition("@")
            if family and not is_family(family):
                return (f"unknown real-scene family {family!r} in {s!r}; expected few<N>, dark, "
                        "rotnoise<deg>, transnoise<frac> or failures")
    bad = [x for x in [*cfg.seeds, *cfg.refine_seeds] if x < 0]
    if bad:
        return f"seeds must be >= 0, got {bad}"
    if "preset" in cfg.overrides:
        return (f"--set preset={cfg.overrides['preset']} is not a field of a point: use "
                "--preset (the base point) or --presets (labelled points)")
    extra = sorted(set(cfg.preset_overrides) - set(cfg.presets))
    if extra:
        return (f"--preset-set names preset(s) {extra} that are not in --presets "
                f"{cfg.presets}: add them to --presets, or --set for every point")
    try:
        plan_points([Path(".")], cfg)
    except ValueError as e:  # an unknown knob, a bad knob value, a bad --set
        return f"invalid evaluation point: {_one_line_validation(e)}"
    return None


def _knob_value(v: str):
    v = v.strip()
    for t in (int, float):
        try:
            return t(v)
        except ValueError:
            pass
    return v


def _deep_merge_dicts(a: dict, b: dict) -> dict:
    from schemas.pipeline import _deep_merge

    return _deep_merge(a, b)


def _defaults(a):
    a.scale_out = a.scale_out or "threads"
    a.workers = a.workers or 2
    return a


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    from flows.reaper import install

    install()  # a temporary Prefect server dies with this process, even after SIGKILL
    try:
        return int(a.fn(a) or 0)
    except BrokenPipeError:  # `freescale scenes show ... | head`: the reader left
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0


if __name__ == "__main__":
    sys.exit(main())
