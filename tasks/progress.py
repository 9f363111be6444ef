"""What a person watching a run sees from inside a task: the scene's ``_work/progress.json``
(read by ``freescale run``), a log line every ``log_every`` seconds in the Prefect task log,
and one Prefect progress artifact per scene and stage (the UI draws it as a bar).

Everything here is best effort: outside a Prefect run context (a plain function call, a unit
test) the log goes to the ``freescale`` logger and no artifact is made; an API error never
fails a stage.
"""

from __future__ import annotations

import logging
import math
import re
import time
from pathlib import Path

from freescale_core.store.progress import PROGRESS_NAME, ProgressFile
from freescale_core.store.store import Store

LOG_EVERY = 10.0  # seconds between progress lines in the task log


def run_logger():
    """The Prefect run logger when inside a run, else a plain logger."""
    try:
        from prefect import get_run_logger

        return get_run_logger()
    except Exception:  # noqa: BLE001 - MissingContextError outside a run
        return logging.getLogger("freescale")


def _artifact_key(scene_id: str, stage: str) -> str:
    k = re.sub(r"[^a-z0-9-]+", "-", f"progress-{scene_id}-{stage}".lower()).strip("-")
    return k[:100]


def _fmt_s(s: float | None) -> str:
    if s is None or not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


def describe(rec: dict) -> str:
    """One line for a progress record: ``reconstruct 1200/15000 steps (8%), ... ETA 3m10s``."""
    done, total = rec.get("done", 0), rec.get("total")
    pct = f" ({100 * done / total:.0f}%)" if total else ""
    info = rec.get("info") or {}
    extra = []
    if "n_gaussians" in info:
        extra.append(f"{int(info['n_gaussians']):,} Gaussians")
    if info.get("loss_ema") is not None:
        extra.append(f"loss {info['loss_ema']:.4f}")
    if info.get("psnr") is not None:
        extra.append(f"~{info['psnr']:.1f} dB")
    if info.get("phase"):
        extra.append(str(info["phase"]))
    if "passed" in info:
        extra.append(f"{info['passed']} passed")
    tail = (", " + ", ".join(extra)) if extra else ""
    eta = rec.get("eta_s")
    return (f"{rec.get('stage')} {done}/{total if total else '?'} {rec.get('unit', '')}{pct}"
            f"{tail}, {_fmt_s(rec.get('elapsed_s'))} elapsed"
            + (f", ETA {_fmt_s(eta)}" if eta is not None else ""))


class StageReporter:
    """Progress of one stage of one scene: file + task log + Prefect progress artifact."""

    def __init__(self, store_root: str, scene_id: str, stage: str, total: int | None = None,
                 unit: str = "items", log_every: float = LOG_EVERY, file_every: float = 1.0):
        self.scene_id, self.stage = scene_id, stage
        work = Store(store_root).work_dir(scene_id, create=True)
        self.file = ProgressFile(Path(work) / PROGRESS_NAME, stage, total, unit, every=file_every)
        self.log = run_logger()
        self.log_every = log_every
        self._last_log = time.monotonic()
        self._artifact = None
        try:
            from prefect.artifacts import create_progress_artifact
            from prefect.context import TaskRunContext

            if TaskRunContext.get() is not None:
                self._artifact = create_progress_artifact(
                    progress=0.0, key=_artifact_key(scene_id, stage),
                    description=f"{scene_id}: {stage}")
        except Exception:  # noqa: BLE001 - no API / no context: no artifact
            self._artifact = None

    def __call__(self, done: int, total: int | None = None, eta_s: float | None = None,
                 **info) -> None:
        force = total is not None and done >= total
        self.file.update(done, total, eta_s=eta_s, force=force, **info)
        now = time.monotonic()
        if force or now - self._last_log >= self.log_every:
            self._last_log = now
            self.log.info("%s: %s", self.scene_id, describe(self.file.record))
            self._update_artifact()

    def _update_artifact(self) -> None:
        if self._artifact is None or not self.file.total:
            return
        try:
            from prefect.artifacts import update_progress_artifact

            pct = min(100.0, 100.0 * self.file.record.get("done", 0) / self.file.total)
            update_progress_artifact(self._artifact, progress=pct)
        except Exception:  # noqa: BLE001
            self._artifact = None

    def finish(self) -> None:
        if self.file.total:
            self.file.update(self.file.total, force=True, **(self.file.record.get("info") or {}))
            self._update_artifact()


def recon_progress(store_root: str, scene_id: str, cfg) -> tuple[StageReporter, callable]:
    """A reporter for the trainer and the ``progress(step, info)`` callback feeding it.

    The trainer stops at ``max_iterations`` or at ``max_seconds`` (or earlier, on a plateau);
    the ETA is the smaller of the step-rate estimate and the remaining time budget.
    """
    rep = StageReporter(store_root, scene_id, "reconstruct", cfg.max_iterations, "steps")
    rep(0, phase="setup (a first run compiles the numba kernels, ~40 s)")
    t0 = time.monotonic()
    first: list[tuple[int, float]] = []  # (step, time) of the first report: the rate after
    # it excludes setup and kernel compilation

    def cb(step: int, info: dict) -> None:
        el = time.monotonic() - t0
        if not first:
            first.append((step, el))
        s0, e0 = first[0]
        eta = (cfg.max_iterations - step) * (el - e0) / (step - s0) if step > s0 else None
        if cfg.max_seconds and eta is not None:
            eta = min(eta, max(0.0, cfg.max_seconds - el))
        total = step if info.get("phase") == "done" else None
        rep(step, total, eta_s=0.0 if total else eta,
            **{k: info[k] for k in ("n_gaussians", "loss_ema", "phase") if k in info})

    return rep, cb
