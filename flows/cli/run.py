"""``freescale run SCENES --store S`` and ``freescale resume STORE``: the generate-dataset flow,
locally, with everything validated first and interrupts marking unfinished scenes failed."""

from __future__ import annotations

import json
import os
import sys
import threading
from pathlib import Path

from flows.cli.common import _parse_set, _version
from flows.cli.scenes import _print_manifest


def add_parsers(sub) -> None:
    from flows.cli.config import help_epilog
    from schemas.pipeline import PRESET_CHOICES

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


def _defaults(a):
    a.scale_out = a.scale_out or "threads"
    a.workers = a.workers or 2
    return a
