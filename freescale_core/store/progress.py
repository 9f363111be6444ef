"""Step-level progress of a running stage, as a small JSON file in the scene's ``_work/``.

A stage calls :meth:`ProgressFile.update` as often as it likes; the file is rewritten
atomically at most every ``every`` seconds (and always on the first and the last update), so
readers (the command line, the Prefect task's log loop, a person with ``cat``) see a complete
record at any instant::

    {"stage": "reconstruct", "done": 1200, "total": 15000, "unit": "steps",
     "started": 1764620000.0, "updated": 1764620061.2, "elapsed_s": 61.2, "eta_s": 540.0,
     "info": {"n_gaussians": 43269, "loss_ema": 0.031, "phase": "grow"}}

``eta_s`` is linear in ``done / total`` unless the caller gives its own (the trainer knows
its time budget). The file is deleted by nobody: the next stage overwrites it and it lives in
``_work/``, which is not part of a published version.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from freescale_core.store.store import write_json_atomic

__all__ = ["ProgressFile", "read_progress", "PROGRESS_NAME"]

PROGRESS_NAME = "progress.json"


class ProgressFile:
    """Throttled, atomic writer of one stage's progress record."""

    def __init__(self, path: str | Path, stage: str, total: int | None = None,
                 unit: str = "items", every: float = 1.0, clock=time.time):
        self.path = Path(path)
        self.stage, self.total, self.unit, self.every = stage, total, unit, float(every)
        self._clock = clock
        self.started = clock()
        self._last_write = -float("inf")
        self.record: dict[str, Any] = {}

    def update(self, done: int, total: int | None = None, eta_s: float | None = None,
               force: bool = False, **info: Any) -> bool:
        """Record ``done`` of ``total``; write the file if ``every`` seconds passed (or
        ``force``). Returns whether the file was written."""
        if total is not None:
            self.total = int(total)
        now = self._clock()
        elapsed = now - self.started
        if eta_s is None and self.total and done > 0:
            eta_s = elapsed * (self.total - done) / done
        self.record = {"stage": self.stage, "done": int(done), "total": self.total,
                       "unit": self.unit, "started": self.started, "updated": now,
                       "elapsed_s": round(elapsed, 2),
                       "eta_s": None if eta_s is None else round(max(0.0, float(eta_s)), 1),
                       "info": {k: _plain(v) for k, v in info.items()}}
        first = self._last_write == -float("inf")
        if not (force or first or now - self._last_write >= self.every):
            return False
        try:
            write_json_atomic(self.path, self.record)
        except OSError:  # progress is a convenience: never fail a stage over it
            return False
        self._last_write = now
        return True


def _plain(v: Any) -> Any:
    if isinstance(v, (bool, int, str)) or v is None:
        return v
    try:
        return round(float(v), 5)
    except (TypeError, ValueError):
        return str(v)


def read_progress(path: str | Path) -> dict | None:
    """The record at ``path``, or None when absent or unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
