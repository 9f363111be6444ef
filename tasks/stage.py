"""The one mechanism every stage task uses: store-backed caching, status and timing.

A stage's cache key is a hash of (stage name, the stage's config, the keys of the stages it
reads, the source of every project module its entry points import transitively and the
versions of torch / numba / pycolmap (:mod:`freescale_core.codekey`), engine version, seed). This is
Prefect's ``INPUTS + TASK_SOURCE`` policy, kept *in the store* instead of the Prefect
server's result storage, for two reasons: the check "is this stage's output in the store
complete?" is part of the key lookup (a deleted or half-written output is recomputed), and
the cache travels with the store to another machine or cluster.

Outputs are written into ``scenes/<id>/_work/`` with atomic renames, and the checkpoint
record is written last, so a process killed at any instant leaves either a complete stage or
none.

``FREESCALE_NOOP_STAGES=1`` (read when this module is imported, so Dask worker processes
started from such an environment honour it too) replaces every stage's work by nothing: the
tasks, their submission, states and store bookkeeping still run, ``publish`` only marks the
scene ok. It exists for the orchestration benchmark (``python -m benchmarks.scale
--orchestration``); a store made this way holds no outputs.
"""

from __future__ import annotations

import os
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from freescale_core import __version__
from freescale_core.errors import FreeScaleError, SceneError
from freescale_core.threads import blas_threads
from freescale_core.store.store import Store, config_hash


# OpenBLAS threads for every stage of every runner (default 1, the selection's own default,
# ``GraphConfig.blas_threads``). Held through the process-wide lease of ``blas_threads``: a
# per-call set/restore (threadpoolctl's ``threadpool_limits``, until stop 30) let a second
# scene's stage switch a running selection's GEMMs from 1 to 2 threads in the thread runner,
# and the stored ``nms_overlap`` came out float32 ulps off the resumed / Dask stores'.
BLAS_THREADS = int(os.environ.get("FREESCALE_BLAS_THREADS", 1))
NOOP_STAGES = os.environ.get("FREESCALE_NOOP_STAGES") == "1"  # the benchmark's no-op mode


def stage_blas_threads():
    """The OpenBLAS lease a stage runs under (``BLAS_THREADS``; the first concurrent holder's
    count is in force, so a selection inside a stage runs at the stage's count)."""
    return blas_threads(BLAS_THREADS)


@dataclass(frozen=True)
class StageRef:
    """What a stage task returns: small, picklable, enough for the next stage to find its
    inputs in the store."""

    scene_id: str
    stage: str
    key: str
    result: dict


def source_hash(roots: tuple[str, ...], root: Path | None = None) -> str:
    """Hash of the source of every project module ``roots`` import, transitively, plus the
    versions of torch, numba and pycolmap (:func:`freescale_core.codekey.code_key`)."""
    from freescale_core.codekey import REPO, code_key

    return code_key(roots, REPO if root is None else root)


def stage_key(stage: str, cfg: Any, upstream: list[StageRef], roots: tuple[str, ...],
              seed: int, root: Path | None = None) -> str:
    """The checkpoint key of ``stage``: its config, its upstream stages' keys (so an edit
    that invalidates a stage invalidates everything after it), the code its entry-point
    modules ``roots`` reach (``root``: the tree to read, the installed one by default) and
    the seed."""
    return config_hash({
        "stage": stage, "cfg": cfg.model_dump(mode="json") if hasattr(cfg, "model_dump") else cfg,
        "upstream": [u.key for u in upstream], "source": source_hash(roots, root),
        "engine": __version__, "seed": seed,
    })


def run_stage(store_root: str, scene_id: str, stage: str, cfg: Any, upstream: list[StageRef],
              roots: tuple[str, ...], seed: int,
              compute: Callable[[Path], tuple[list[str], dict]]) -> StageRef:
    """Run ``compute(work_dir) -> (files, result)`` unless a complete checkpoint exists.

    Records seconds and counts in the scene's status; on failure marks the scene failed with
    an error that names the scene, the stage and (for input errors) the file, then re-raises.
    """
    store = Store(store_root)
    key = stage_key(stage, cfg, upstream, roots, seed)
    if NOOP_STAGES:  # the benchmark's no-op mode: its checkpoints never match a real run's
        compute, key = _noop, f"noop-{key}"
    done = store.stage_done(scene_id, stage, key)
    if done is not None:
        result = done.get("result", {})
        # A run killed between the checkpoint and the status update left the status without
        # this stage's counts; restore them from the checkpoint (idempotent).
        st = store.read_status(scene_id)
        counts = _counts(result)
        if (any(st.get("counts", {}).get(k) != v for k, v in counts.items())
                or stage not in st.get("seconds", {})):
            store.update_status(scene_id, counts=counts,
                                seconds={stage: float(done.get("seconds", 0.0))})
        _log_stage(scene_id, stage, float(done.get("seconds", 0.0)), result, reused=True)
        return StageRef(scene_id, stage, key, result)
    store.update_status(scene_id, status="running", stage=stage)
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        # Dask workers start with OMP/OPENBLAS_NUM_THREADS=1, the thread runner with one per
        # core; a float32 GEMM summed by a different number of threads differs in the last
        # bits. Pin OpenBLAS so every runner (threads, local Dask, a cluster of like machines)
        # writes the same store.
        with stage_blas_threads():
            files, result = compute(store.work_dir(scene_id, create=True))
    except BaseException as e:  # includes KeyboardInterrupt: record, then propagate
        mark_failed(store, scene_id, stage, e)
        raise
    seconds = time.perf_counter() - t0
    # process CPU seconds while the stage ran (all threads; a stage's own only when one scene
    # runs at a time, as in the evaluate-engine flow)
    cpu = time.process_time() - c0
    store.mark_stage_done(scene_id, stage, key, files, result, seconds=seconds)
    store.update_status(scene_id, seconds={stage: seconds}, counts=_counts(result),
                        info={f"cpu_seconds_{stage}": cpu})
    _log_stage(scene_id, stage, seconds, result)
    return StageRef(scene_id, stage, key, result)


def _noop(work: Path) -> tuple[list[str], dict]:
    return [], {}


def _log_stage(scene_id: str, stage: str, seconds: float, result: dict,
               reused: bool = False) -> None:
    """One line in the task log: the stage's counts and seconds."""
    from tasks.progress import run_logger

    c = _counts(result) or {f"n_{k}": v for k, v in result.items()
                            if isinstance(v, (int, bool)) and not k.startswith("_")}
    counts = ", ".join(f"{k[2:]}={v}" for k, v in c.items())
    extra = [f"{k}={result[k]:.2f}" for k in ("recon_train_psnr", "recon_test_psnr")
             if isinstance(result.get(k), float)]
    what = "reused checkpoint" if reused else "done"
    run_logger().info("%s: %s %s in %.1f s%s", scene_id, stage, what, seconds,
                      f" ({', '.join(filter(None, [counts, *extra]))})" if counts or extra else "")


def _counts(result: dict) -> dict:
    return {k: v for k, v in result.items() if k.startswith("n_") and isinstance(v, (int, float))}


def mark_failed(store: Store, scene_id: str, stage: str, e: BaseException) -> None:
    if isinstance(e, SceneError):
        msg = str(e)
    elif isinstance(e, FreeScaleError):
        msg = f"scene '{scene_id}': {e}"
    else:
        tb = traceback.extract_tb(e.__traceback__)
        where = f" at {Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else ""
        msg = f"scene '{scene_id}': {type(e).__name__}: {e}{where}"
    store.update_status(scene_id, status="failed", error=f"[{stage}] {msg}",
                        error_type=type(e).__name__, stage=stage)
