"""The ``generate-dataset`` flow: scenes in, a FreeScale store out.

The flow only orders tasks (``tasks/``); all work happens in ``freescale_core``. Per scene the
chain is ingest -> reconstruct -> select -> freeviews -> publish (the stage names of the
tasks, the checkpoint keys and docs/ARCHITECTURE.md); chains of
different scenes run concurrently on the chosen task runner (threads by default, or Dask
worker processes / an existing Dask cluster). A failing scene is marked failed in the
manifest with its error; the others finish; the run then ends in a Failed state naming the
failed scenes. Re-running on the same store re-executes only scenes that are not ``ok`` with
the same config, and within a scene only stages without a complete checkpoint.
"""

from __future__ import annotations

import glob
import hashlib
import os
from pathlib import Path
from typing import Literal

from prefect import flow, get_run_logger
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.states import Completed, Failed

from freescale_core.store.store import MANIFEST_VIEW, Store, config_hash, write_json_atomic
from schemas.pipeline import PipelineConfig
from tasks.scene_tasks import freeviews, ingest, publish, reconstruct, select

ScaleOut = Literal["threads", "dask"]


class ScenesFailed(RuntimeError):
    """The flow's failure: some scenes failed; ``summary`` is the run summary dict."""

    def __init__(self, message: str, summary: dict):
        super().__init__(message)
        self.summary = summary


def expand_scenes(scenes: list[str] | str) -> list[Path]:
    """Expand folders and globs into scene folders, sorted, without duplicates."""
    if isinstance(scenes, (str, Path)):
        scenes = [str(scenes)]
    out: list[Path] = []
    for s in scenes:
        matches = sorted(glob.glob(os.path.expanduser(str(s)))) if glob.has_magic(str(s)) else [s]
        if not matches:
            raise FileNotFoundError(f"no scene folder matches {s!r}")
        for m in matches:
            p = Path(m).resolve()
            if p.is_dir() and p not in out:
                out.append(p)
            elif not p.is_dir() and not glob.has_magic(str(s)):
                raise FileNotFoundError(f"scene folder not found: {p}")
    return out


def scene_ids_for(paths: list[Path]) -> list[str]:
    """Scene ids = folder names; folders sharing a name all get enough parent folder names
    prepended (``a__b__colmap_small``) to be unique, and a short hash of the path if even
    that does not separate them. Every clashing folder is renamed, decided on the original
    names (so no folder keeps the bare name by accident of order)."""
    paths = [Path(p) for p in paths]
    ids = [p.name for p in paths]
    depth = 1
    while len(set(ids)) != len(ids) and depth <= 4:
        clash = {i for i in ids if ids.count(i) > 1}
        ids = [("__".join([*p.parts[-1 - depth:-1], p.name]) if i in clash else i)
               for i, p in zip(ids, paths)]
        depth += 1
    if len(set(ids)) != len(ids):
        ids = [f"{i}-{hashlib.sha256(str(p).encode()).hexdigest()[:6]}"
               if ids.count(i) > 1 else i for i, p in zip(ids, paths)]
    if len(set(ids)) != len(ids):
        raise ValueError(f"scene ids are not unique: {ids}")
    return ids


def assign_scene_ids(paths: list[Path], st: Store) -> tuple[list[str], list[str]]:
    """Scene ids for ``paths`` in store ``st``: :func:`scene_ids_for`, except that an id the
    store already holds for *another* source folder is never reused (its results stay): the
    folder gets ``<parent>__<name>`` or a hashed id instead. Returns ``(ids, notes)``."""
    ids = scene_ids_for(paths)
    notes = []
    taken = set(ids)
    for k, (sid, p) in enumerate(zip(ids, paths)):
        prev = st.read_status(sid).get("source")
        if not prev or Path(prev) == Path(p):
            continue
        tag = hashlib.sha256(str(p).encode()).hexdigest()[:6]
        for alt in (f"{p.parent.name}__{p.name}", f"{p.name}-{tag}", f"{sid}-{tag}"):
            other = st.read_status(alt).get("source")
            if alt not in taken and (not other or Path(other) == Path(p)):
                break
        else:
            raise ValueError(f"no free scene id for {p} in {st.root}")
        notes.append(f"scene id {sid!r} in this store holds {prev}; {p} is stored as {alt!r}")
        taken.discard(sid)
        taken.add(alt)
        ids[k] = alt
    return ids, notes


def make_task_runner(scale_out: ScaleOut, dask_address: str | None, n_workers: int):
    if scale_out == "threads":
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=max(1, n_workers))
    if scale_out == "dask":
        from prefect_dask import DaskTaskRunner

        if dask_address:
            return DaskTaskRunner(address=dask_address)
        # Local cluster: worker processes, every socket on loopback, no dashboard; the workers
        # report to this process's Prefect server (without it each started a temporary server
        # of its own, ~220 MB, whose task runs the flow's UI never showed).
        return DaskTaskRunner(cluster_kwargs={
            "n_workers": n_workers, "threads_per_worker": 1, "processes": True,
            "host": "127.0.0.1", "dashboard_address": None,
            "worker_dashboard_address": None, "env": _prefect_env_for_workers(),
        })
    raise ValueError(f"scale_out must be 'threads' or 'dask', got {scale_out!r}")


def _prefect_env_for_workers() -> dict[str, str]:
    """``PREFECT_API_URL`` of the temporary server this process runs (none when the user set
    one: workers inherit it). Prefect keeps its temporary servers by port; the running one is
    the flow's."""
    if os.environ.get("PREFECT_API_URL"):
        return {}
    try:
        from prefect.server.api.server import SubprocessASGIServer
    except ImportError:  # pragma: no cover - another Prefect layout
        return {}
    running = [s for s in SubprocessASGIServer._instances.values() if s.running]
    return {"PREFECT_API_URL": running[0].api_url} if len(running) == 1 else {}


@flow(name="run-scenes", log_prints=True)
def run_scenes(work: list[dict], store: str, cfg: PipelineConfig, cfg_hash: str) -> list[dict]:
    """Run every scene's stage chain; return one record per scene.

    A stage is submitted only once the stage before it has finished, so every task the runner
    holds is ready to run: ``n_workers`` scenes really proceed at once. (Submitting whole
    chains of futures made each waiting stage hold a worker thread, and the scenes ran one
    after the other.) A failed stage ends its scene; the store's status says why.
    """
    from prefect.futures import as_completed

    # (stage, submit(scene_id, folder, results of the earlier stages by name)), in order
    chain = [
        ("ingest", lambda sid, p, r: ingest.submit(store, sid, p, cfg)),
        ("reconstruct", lambda sid, p, r: reconstruct.submit(store, r["ingest"], p, cfg)),
        ("select", lambda sid, p, r: select.submit(store, r["ingest"], r["reconstruct"], cfg)),
        ("freeviews", lambda sid, p, r: freeviews.submit(
            store, r["ingest"], r["reconstruct"], r["select"], p, cfg)),
        ("publish", lambda sid, p, r: publish.submit(
            store, r["ingest"], r["reconstruct"], r["select"], r["freeviews"], cfg, cfg_hash,
            p)),
    ]
    done: dict[str, dict] = {w["scene_id"]: {} for w in work}
    paths = {w["scene_id"]: w["path"] for w in work}
    running = {chain[0][1](sid, paths[sid], {}): sid for sid in done}
    crashed: dict[str, str] = {}
    while running:
        fut = next(as_completed(list(running)))
        sid = running.pop(fut)
        try:
            result = fut.result()
        except BaseException as e:  # noqa: BLE001 - the stage recorded its error in the store
            crashed[sid] = f"{chain[len(done[sid])][0]}: {type(e).__name__}: {e}"[:300]
            continue
        k = len(done[sid])
        done[sid][chain[k][0]] = result
        if k + 1 < len(chain):
            running[chain[k + 1][1](sid, paths[sid], done[sid])] = sid
    out = []
    st = Store(store)
    for sid in done:
        status = st.read_status(sid)
        if status.get("status") not in ("ok", "failed"):
            # the task ended without recording why (a crash outside the stage: Prefect, the
            # worker): the scene must not stay 'pending' / 'running' in the store
            err = (f"scene '{sid}': did not finish: {crashed.get(sid, 'no result')} "
                   "(see the Prefect task logs)")
            st.update_status(sid, status="failed", error=err, error_type="Crashed")
            status = st.read_status(sid)
        if status.get("status") != "ok":
            status.setdefault("error", "did not finish (see the Prefect task logs)")
        out.append({"scene_id": sid, "status": status.get("status", "failed"),
                    "error": status.get("error", ""),
                    "empty_reason": (status.get("info") or {}).get("empty_reason", "")})
    return out


@flow(name="generate-dataset", log_prints=True)
def generate_dataset(
    scenes: list[str],
    store: str = "data/store",
    config: PipelineConfig | None = None,
    scale_out: ScaleOut = "threads",
    n_workers: int = 2,
    dask_address: str | None = None,
    force: bool = False,
) -> dict:
    """Generate free views for every scene into ``store``.

    Args:
        scenes: scene folders or globs (COLMAP ``sparse/``, ``transforms.json`` or images).
        store: output store folder (local or shared file system).
        config: the pipeline config (``schemas/pipeline.py``). A partial one starts from its
            preset: ``{"preset": "fast", "select": {"nms": {"max_views": 200}}}``. Presets:
            ``auto`` (the default: ``paper`` with CUDA, ``cpu`` without), ``paper`` (the
            paper's numbers), ``cpu`` (paper selection, CPU-sized reconstruction), ``fast``
            (small, for tests and demos).
        scale_out: ``threads`` (this process) or ``dask`` (worker processes or a cluster).
        n_workers: concurrent scenes (threads or local Dask workers).
        dask_address: ``tcp://host:8786`` of an existing Dask cluster (with ``scale_out=dask``).
        force: re-run scenes that are already ``ok`` with the same config.
    Returns:
        ``{"ok": [...], "failed": [...], "skipped": [...], "store": store}``; the flow run ends
        Failed (with this summary in its message) when any scene failed.
    """
    log = get_run_logger()
    cfg = config if config is not None else PipelineConfig.from_preset("auto")
    h = config_hash(cfg)
    paths = expand_scenes(scenes)
    st = Store(store)
    ids, notes = assign_scene_ids(paths, st)
    for n in notes:
        log.warning(n)
    _write_run_config(store, paths, cfg, scale_out, n_workers, dask_address)
    log.info("preset %s (config %s); `freescale config show --preset %s` lists every field",
             cfg.preset, h, cfg.preset)
    work, skipped = [], []
    from freescale_core.scene.fingerprint import input_fingerprint

    # one writer per scene: a scene another run is writing is left to it (a clear error)
    locks, busy = _lock_scenes(st, ids, log)
    try:
        for sid, p in zip(ids, paths):
            if sid in busy:
                continue
            prev = st.read_status(sid)
            fp = input_fingerprint(p)
            # complete = same config, same source folder, same input contents, published
            if (not force and prev.get("status") == "ok" and prev.get("config_hash") == h
                    and prev.get("source") == str(p) and prev.get("input_fingerprint") == fp
                    and _published(st, sid, log)):
                skipped.append(sid)
                continue
            st.update_status(sid, status="pending", error="", error_type="", source=str(p),
                             config_hash=h, input_fingerprint=fp)
            work.append({"scene_id": sid, "path": str(p)})
        log.info("%d scenes: %d to run, %d already complete (config %s)", len(ids), len(work),
                 len(skipped), h)
        results = run_scenes.with_options(
            task_runner=make_task_runner(scale_out, dask_address, n_workers))(
                work, store, cfg, h) if work else []
    finally:
        locks.close()
    results = results + [{"scene_id": sid, "status": "busy", "error": err, "empty_reason": ""}
                         for sid, err in busy.items()]
    ok = [r["scene_id"] for r in results if r["status"] == "ok"]
    failed = [r for r in results if r["status"] != "ok"]
    empty = {r["scene_id"]: r["empty_reason"] for r in results
             if r["status"] == "ok" and r.get("empty_reason")}
    summary = {"ok": ok, "failed": [f["scene_id"] for f in failed], "skipped": skipped,
               "empty": empty, "store": str(store), "config_hash": h}
    st.compile_manifest()
    _publish_artifacts(st, summary, failed)
    # a scene with 0 free views is ok (complete, published) but never reported as plain ok
    empty_msg = ("; " + f"{len(empty)} with 0 free views: " + "; ".join(
        f"{sid} ({why})" for sid, why in empty.items())) if empty else ""
    if failed:
        names = ", ".join(f"{f['scene_id']} ({f['error'][:200]})" for f in failed)
        msg = f"{len(failed)} of {len(ids)} scenes failed: {names}{empty_msg}"
        # the data of a Failed state must be an exception: a served or worker-run flow
        # resolves it, and a dict crashed the engine ("dict cannot be resolved into an
        # exception"); the summary rides on it
        return Failed(message=msg, data=ScenesFailed(msg, summary))
    return Completed(message=f"{len(ok)} scenes ok, {len(skipped)} already complete{empty_msg}",
                     data=summary)


def _published(st: Store, sid: str, log) -> bool:
    """The scene's CURRENT names a version folder that exists. A deleted version folder is
    not complete: the scene runs again (was: the flow failed and the CLI suggested the same
    resume again)."""
    from freescale_core.errors import StoreError

    try:
        return st.current_version_dir(sid) is not None
    except StoreError as e:
        log.warning("%s: running the scene again", e)
        return False


def _lock_scenes(st: Store, ids: list[str], log):
    """Take every scene's writer lock (:meth:`Store.scene_writer`): ``(ExitStack holding
    them, {scene_id: error} of the scenes another run holds)``."""
    import contextlib

    from freescale_core.store.store import SceneBusyError

    locks, busy = contextlib.ExitStack(), {}
    try:
        for sid in ids:
            try:
                locks.enter_context(st.scene_writer(sid))
            except SceneBusyError as e:
                log.error("%s", e)
                busy[sid] = str(e)
    except BaseException:
        locks.close()
        raise
    return locks, busy


def _write_run_config(store: str, scenes, cfg: PipelineConfig, scale_out: str, n_workers: int,
                      dask_address: str | None) -> None:
    """``run_config.json``: how this store was made, so ``freescale resume STORE`` works on a
    store made by any caller (the command line adds its preset and ``--set`` overrides)."""
    import json

    from freescale_core.store.store import read_store_file, write_store_file

    try:
        blob = read_store_file(store, "run_config.json")
        prev = json.loads(blob) if blob else {}
    except ValueError:
        prev = {}
    # absolute folders (resume works from any directory), merged with earlier runs' scenes
    # (resume still retries an earlier run's failures); the latest config applies to all
    remembered: list[str] = []
    for x in list(prev.get("scenes", [])) + [str(s) for s in scenes]:
        for y in ([Path(m).resolve() for m in sorted(glob.glob(x))] if glob.has_magic(x)
                  else [Path(x).resolve()]):
            if str(y) not in remembered:
                remembered.append(str(y))
    prev.update({"scenes": remembered,
                 "preset": cfg.preset, "config": cfg.model_dump(mode="json"),
                 "scale_out": scale_out, "workers": n_workers, "dask_address": dask_address})
    prev.setdefault("overrides", {})
    write_store_file(store, "run_config.json",
                     json.dumps(prev, indent=2, sort_keys=True).encode())


def _publish_artifacts(st: Store, summary: dict, failed: list[dict]) -> None:
    """A table artifact of the manifest and a markdown summary, for the Prefect UI."""
    rows = st.manifest().to_pylist()
    keep = MANIFEST_VIEW
    table = [{k: r.get(k) for k in keep if k in r} for r in rows]
    try:
        if table:
            create_table_artifact(table=table, key="freescale-manifest",
                                  description=f"Manifest of {summary['store']}")
        md = [f"# generate-dataset: {summary['store']}", "",
              f"- ok: {len(summary['ok'])}", f"- failed: {len(summary['failed'])}",
              f"- already complete (skipped): {len(summary['skipped'])}",
              f"- ok with 0 free views: {len(summary.get('empty', {}))}",
              f"- config hash: `{summary['config_hash']}`", ""]
        if summary.get("empty"):
            md += ["## Scenes with 0 free views", "", "| scene | why |", "|---|---|"]
            md += [f"| {k} | {v.replace('|', '/')} |" for k, v in summary["empty"].items()]
            md += [""]
        if failed:
            md += ["## Failed scenes", "", "| scene | error |", "|---|---|"]
            md += [f"| {f['scene_id']} | {f['error'].replace('|', '/')[:300]} |" for f in failed]
        md += ["", f"Browse: `freescale scenes ls {summary['store']}`; figures of every scene: "
               f"`freescale report {summary['store']}` (and the per-scene artifacts)."]
        create_markdown_artifact(markdown="\n".join(md), key="freescale-run-summary")
    except Exception as e:  # artifacts are a convenience; never fail a run over them
        get_run_logger().warning("could not create artifacts: %s", e)
