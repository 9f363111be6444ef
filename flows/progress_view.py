"""``freescale run``'s live progress: polls the store (``status.json`` and the running stage's
``_work/progress.json`` of every scene) and shows it.

* On a terminal: rich bars, one for the scenes and one per running scene (stage, step or
  views done / total, Gaussians, loss, ETA); Prefect's log lines are printed *above* the bars
  (the Prefect console handler is pointed at the bars' console while they are live).
* Piped or logged: one plain line every ``every`` seconds per running scene, and one line
  when a scene finishes, so a 10-minute reconstruction is never silent.
"""

from __future__ import annotations

import glob
import logging
import os
import sys
import threading
import time
from pathlib import Path

from freescale_core.store.progress import PROGRESS_NAME, read_progress
from freescale_core.store.store import Store
from tasks.progress import describe

__all__ = ["ProgressView", "numba_cache_cold", "FIRST_RUN_NOTE"]

FIRST_RUN_NOTE = ("first run on this machine: numba compiles the rasterizer and selection "
                  "kernels once (~40 s on 2 cores, nothing is printed meanwhile); later runs "
                  "load them from the cache")


def numba_cache_cold() -> bool:
    """True when no compiled rasterizer kernel is cached yet (the first run compiles them)."""
    import freescale_core.raster.kernels as k

    dirs = [Path(k.__file__).parent / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        dirs.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    return not any(glob.glob(str(d / "**" / "kernels*.nbi"), recursive=True) for d in dirs)


def _snapshot(st: Store, ids: list[str]) -> tuple[list[str], dict[str, dict]]:
    """(finished scene ids, {running scene id: progress record or {'stage': ...}})."""
    done, running = [], {}
    for s in ids:
        status = st.read_status(s)
        if status.get("status") in ("ok", "failed"):
            done.append(s)
        elif status.get("status") == "running":
            rec = read_progress(st.work_dir(s) / PROGRESS_NAME) or {}
            stage = status.get("stage") or "starting"
            if rec.get("stage") != stage:
                rec = {"stage": stage}  # a stage without step progress (ingest, select, ...)
            running[s] = rec
    return done, running


class ProgressView:
    """Run it around a blocking call: ``with ProgressView(store, ids): run()``."""

    def __init__(self, store_root: str, scene_ids: list[str], tty: bool | None = None,
                 every: float = 5.0, stream=None):
        self.st = Store(store_root)
        self.ids = list(scene_ids)
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty() if tty is None else tty
        self.every = every
        self._stop = threading.Event()
        self._th: threading.Thread | None = None
        self._handlers: list[tuple[logging.Handler, object]] = []

    # ---- plain lines (pipes, CI logs)
    def _plain(self) -> None:
        t0 = time.monotonic()
        reported: set[str] = set()
        last = -1e9
        while True:
            stopping = self._stop.wait(0.5)
            done, running = _snapshot(self.st, self.ids)
            for s in done:
                if s not in reported:
                    reported.add(s)
                    status = self.st.read_status(s)
                    n = status.get("counts", {}).get("n_free_views")
                    what = (f"{n} free views" if status.get("status") == "ok"
                            else (status.get("error") or "")[:160])
                    self._line(f"[{time.monotonic() - t0:6.0f}s] {s}: {status.get('status')} "
                               f"({what}) [{len(reported)}/{len(self.ids)} scenes]")
            if time.monotonic() - last >= self.every:
                last = time.monotonic()
                for s, rec in running.items():
                    msg = describe(rec) if "done" in rec else f"{rec.get('stage')} running"
                    self._line(f"[{time.monotonic() - t0:6.0f}s] {s}: {msg}")
            if stopping:
                return

    def _line(self, text: str) -> None:
        print(text, file=self.stream, flush=True)

    # ---- rich bars (terminal)
    def _bars(self) -> None:
        from rich.console import Console
        from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn,
                                   TimeElapsedColumn)

        con = Console(file=self.stream)
        self._route_logs(con)
        try:
            with Progress(TextColumn("{task.description}", style="bold", markup=False),
                          BarColumn(bar_width=24), MofNCompleteColumn(), TimeElapsedColumn(),
                          TextColumn("{task.fields[extra]}", markup=False),
                          console=con, transient=False) as prog:
                top = prog.add_task("scenes", total=len(self.ids), extra="")
                per: dict[str, int] = {}
                while True:
                    stopping = self._stop.wait(0.5)
                    done, running = _snapshot(self.st, self.ids)
                    prog.update(top, completed=len(done))
                    for s, rec in running.items():
                        if s not in per:
                            per[s] = prog.add_task(s, total=None, extra="")
                        info = describe(rec).split(", ", 1)[1] if "done" in rec else "running"
                        prog.update(per[s], description=f"{s}: {rec.get('stage')}",
                                    total=rec.get("total") or None,
                                    completed=rec.get("done", 0), extra=info)
                    for s in list(per):
                        if s not in running:
                            prog.remove_task(per.pop(s))
                    if stopping:
                        return
        finally:
            self._unroute_logs()

    def _route_logs(self, con) -> None:
        """Print Prefect's console log lines through the bars' console (above the bars)."""
        for lg in (logging.getLogger(), logging.getLogger("prefect")):
            for h in lg.handlers:
                if hasattr(h, "console") and type(h).__name__ == "PrefectConsoleHandler":
                    self._handlers.append((h, h.console))
                    h.console = con

    def _unroute_logs(self) -> None:
        for h, old in self._handlers:
            h.console = old
        self._handlers.clear()

    def __enter__(self):
        self._th = threading.Thread(target=self._bars if self.tty else self._plain, daemon=True)
        self._th.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._th is not None:
            self._th.join(timeout=10)
        return False
