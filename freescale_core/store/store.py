"""The FreeScale store: one folder per run target, readable while it is being written.

Layout (documented for users in ``docs/STORE.md``)::

    STORE/
      manifest.parquet                 one row per scene (compiled from the status files)
      scenes/<scene_id>/
        status.json                    the scene's truth: status, error, counts, seconds ...
        CURRENT                        names the published version folder, e.g. "v0003"
        v0003/                         a published, complete version (never modified)
          views.parquet                one row per camera (training + candidates)
          view_graph.parquet           src, dst, wiou
          arrays.zarr/                 certainty [R,R,R] (+ bbox attrs), freeviews/{rgb,depth}
          gaussians.ply                (when reconstruction ran here)
          *.png                        pictures: cameras, certainty projections, contact sheet
        _work/                         per-stage checkpoints (each written atomically)

Atomicity rules:

* every file is written to a temporary name in the same folder and ``os.replace``-d;
* a scene's published outputs are built in a fresh version folder and become visible by
  atomically replacing ``CURRENT``; readers resolve ``CURRENT`` first, so they see either
  the previous complete version or the new complete version, never a mixture;
* ``manifest.parquet`` is recompiled from all ``status.json`` files under a file lock and
  replaced atomically, so concurrent workers (threads, Dask processes) never lose updates.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import json
import os
import shutil
import socket
import stat as _stat
import tempfile
import uuid
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from freescale_core import __version__
from freescale_core.errors import StoreError

STATUSES = ("pending", "running", "ok", "failed")


# The manifest's columns a person looks for first (``scenes ls``, the Prefect artifact): the
# free-view count, scarcity, reconstruction quality.
MANIFEST_VIEW = ("scene_id", "status", "n_images", "n_gaussians", "n_candidates", "n_selected",
                 "n_free_views", "empty_reason", "scarce", "recon_train_psnr", "recon_test_psnr",
                 "seconds_total", "error")


class SceneBusyError(StoreError):
    """Another run holds the scene's writer lock (:meth:`Store.scene_writer`)."""



# --------------------------------------------------------------------------- atomic files
from freescale_core.files import (HOST, _json_default, atomic_path, clean_stale_temps,  # noqa: E402,F401
                                  write_bytes_atomic, write_json_atomic, writer_gone)


def write_parquet_atomic(path: str | Path, table: pa.Table) -> None:
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)




def config_hash(obj: Any) -> str:
    """Stable short hash of a JSON-able config (pydantic models: ``model_dump(mode='json')``)."""
    if hasattr(obj, "model_dump"):
        obj = obj.model_dump(mode="json")
    blob = json.dumps(obj, sort_keys=True, default=_json_default).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


# --------------------------------------------------------------------------- owned bytes
FICLONE = 0x40049409  # linux/fs.h: share the extents copy-on-write (btrfs, XFS, ...)


def own_copy(src: str | Path, dst: str | Path) -> None:
    """Put a copy of ``src`` at ``dst`` that ``dst`` owns: editing either never changes the
    other. A reflink where the file system has one (instant, no extra space), else a byte
    copy; a symlink is followed (the copy holds the target's bytes)."""
    src, dst = Path(src), Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        with open(src, "rb") as fi, open(dst, "wb") as fo:
            fcntl.ioctl(fo.fileno(), FICLONE, fi.fileno())
        shutil.copystat(src, dst)
        return
    except OSError:
        pass
    shutil.copy2(src, dst)


def link_store_file(src: str | Path, dst: str | Path) -> None:
    """Hard-link a file the store itself wrote and never rewrites in place (its checkpoints
    are replaced atomically: a new file, so the link keeps the old bytes); else
    :func:`own_copy`. Never for a user's file."""
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        own_copy(src, dst)


# --------------------------------------------------------------------------- what is data
def is_store(p: str | Path) -> bool:
    """A FreeScale store: a ``scenes/`` folder beside its manifest, lock, or a scene status."""
    p = Path(p)
    if not (p / "scenes").is_dir():
        return False
    if (p / "manifest.parquet").is_file() or (p / ".lock").is_file():
        return True
    return any((q / "status.json").is_file() for q in (p / "scenes").iterdir())


def is_shards(p: str | Path) -> bool:
    """A shards folder (``freescale shards pack``): ``shards/`` beside ``manifest.parquet``."""
    p = Path(p)
    return (p / "shards").is_dir() and (p / "manifest.parquet").is_file()


def _kind(p: Path) -> str | None:
    return "store" if is_store(p) else "shards folder" if is_shards(p) else None


def data_around(path: str | Path, below: bool = True) -> str | None:
    """Why ``path`` must not be replaced or deleted: it is, lies inside or (``below``) holds
    a store or a shards folder. ``None`` when it does none of these."""
    path = Path(path).absolute()
    for q in (path, *path.parents):
        k = _kind(q)
        if k is not None:
            return f"{path} is a {k}" if q == path else f"{path} lies inside the {k} {q}"
    if below and path.is_dir():
        for d, subs, _ in os.walk(path):  # symlinks are not followed
            for name in list(subs):
                k = _kind(Path(d) / name)
                if k is not None:
                    return f"{path} holds the {k} {Path(d) / name}"
    return None


# --------------------------------------------------------------------------- the store
class Store:
    """A FreeScale output store rooted at ``root`` (created on first write): a folder, a
    ``file://`` URL, or an object-store URL (``s3://bucket/store``: an
    :class:`~freescale_core.store.objstore.ObjectStore`)."""

    def __new__(cls, root: str | Path = "."):
        if cls is Store and is_url(root):
            return super().__new__(ObjectStore)
        return super().__new__(cls)

    def __init__(self, root: str | Path):
        if isinstance(root, str) and root.startswith("file://"):
            root = root[len("file://"):]
        self.root = Path(root)

    def __str__(self) -> str:
        return str(self.root)

    # ---- layout
    @property
    def manifest_path(self) -> Path:
        return self.root / "manifest.parquet"

    def scene_dir(self, scene_id: str) -> Path:
        return self.root / "scenes" / scene_id

    def work_dir(self, scene_id: str, create: bool = False) -> Path:
        """The scene's stage-checkpoint folder; created only when ``create`` (write paths):
        reading a store never adds folders to it."""
        d = self.scene_dir(scene_id) / "_work"
        if create:
            d.mkdir(parents=True, exist_ok=True)
        return d

    def scene_ids(self) -> list[str]:
        return sorted(self._status_stats())

    def _status_stats(self) -> dict[str, os.stat_result]:
        """{scene id: ``os.stat`` of its ``status.json``} in one pass over ``scenes/``
        (``os.scandir`` and string paths: at 10,000 scenes the ``pathlib`` objects of this
        walk cost more than the system calls)."""
        d = os.path.join(self.root, "scenes")
        out: dict[str, os.stat_result] = {}
        try:
            it = os.scandir(d)
        except (FileNotFoundError, NotADirectoryError):
            return out
        with it:
            for e in it:
                try:
                    s = os.stat(os.path.join(e.path, "status.json"))
                except (FileNotFoundError, NotADirectoryError):
                    continue
                if _stat.S_ISREG(s.st_mode):
                    out[e.name] = s
        return out

    # ---- status (per scene truth) and manifest (compiled view)
    @contextlib.contextmanager
    def _lock(self) -> Iterator[None]:
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / ".lock", "a+") as f:
            fcntl.flock(f.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)

    def read_status(self, scene_id: str) -> dict:
        p = self.scene_dir(scene_id) / "status.json"
        if not p.is_file():
            return {}
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError as e:  # never happens with atomic writes; say so loudly
            raise StoreError(f"status file is not valid JSON: {p}: {e}") from e

    def update_status(self, scene_id: str, **fields: Any) -> dict:
        """Merge ``fields`` into the scene's status (dict fields are merged one level deep).
        Returns the new status.

        Only the scene's ``status.json`` is written (constant cost per call); the manifest is
        compiled from the status files when it is read and is older than any of them."""
        with self._lock():
            st = self.read_status(scene_id)
            if not st:
                st = {"scene_id": scene_id, "status": "pending", "error": "", "counts": {},
                      "seconds": {}, "info": {}, "engine_version": __version__}
            for k, v in fields.items():
                if isinstance(v, dict) and isinstance(st.get(k), dict):
                    st[k] = {**st[k], **v}
                else:
                    st[k] = v
            if st.get("status") not in STATUSES:
                raise StoreError(f"bad status {st.get('status')!r} for scene {scene_id}")
            st["updated_at"] = _now()
            st["engine_version"] = __version__
            self._write_status(scene_id, st)
        return st

    def _write_status(self, scene_id: str, st: dict) -> None:
        write_json_atomic(self.scene_dir(scene_id) / "status.json", st)

    def manifest_stale(self) -> bool:
        """True when a status file is newer than ``manifest.parquet`` (or it is missing)."""
        return self._stale(self._status_stats())

    def _stale(self, stats: dict[str, os.stat_result]) -> bool:
        try:
            t = os.stat(self.manifest_path).st_mtime_ns
        except FileNotFoundError:
            return bool(stats)
        return any(s.st_mtime_ns >= t for s in stats.values())

    def _table_of(self, ids: list[str]) -> pa.Table:
        """The manifest of scenes ``ids``, read from their status files."""
        scenes = os.path.join(self.root, "scenes")
        rows = []
        for sid in ids:
            p = os.path.join(scenes, sid, "status.json")
            try:
                with open(p, "rb") as f:
                    blob = f.read()
            except FileNotFoundError:  # removed since the listing: as read_status, {}
                blob = b"{}"
            try:
                rows.append(_manifest_row(json.loads(blob)))
            except json.JSONDecodeError as e:  # never happens with atomic writes
                raise StoreError(f"status file is not valid JSON: {p}: {e}") from e
        return _rows_to_table(rows, MANIFEST_FIRST, MANIFEST_FLOAT)

    def compile_manifest(self) -> None:
        """Rebuild ``manifest.parquet`` from every ``status.json`` (atomic, under the lock)."""
        with self._lock():
            table = self._table_of(self.scene_ids())
            write_parquet_atomic(self.manifest_path, table)

    def manifest(self) -> pa.Table:
        """The manifest table, compiled first when stale (an empty table for a new store)."""
        stats = self._status_stats()
        if self._stale(stats):
            try:
                self.compile_manifest()
            except OSError:  # a read-only store: compile in memory
                return self._table_of(sorted(stats))
        if not self.manifest_path.is_file():
            return _rows_to_table([], MANIFEST_FIRST, MANIFEST_FLOAT)
        # one file: ParquetFile reads it as read_table does, without importing pyarrow.dataset
        # (0.3 s of the first call)
        return pq.ParquetFile(self.manifest_path).read()

    # ---- one writer per scene
    @contextlib.contextmanager
    def scene_writer(self, scene_id: str, wait: float = 0.0) -> Iterator[None]:
        """Hold the scene's writer lock (``scenes/<id>/.writer.lock``, an exclusive
        ``flock``: released by the kernel when the holder dies) while a run writes the scene,
        so two runs never mix their stage outputs and configs in one version.

        Args:
            wait: seconds to wait for another writer to finish (0: fail at once).
        Raises:
            SceneBusyError: another process holds the lock (its pid, host and start time in
                the message).
        """
        import time

        d = self.scene_dir(scene_id)
        d.mkdir(parents=True, exist_ok=True)
        f = open(d / ".writer.lock", "a+")
        deadline = time.monotonic() + max(0.0, float(wait))
        try:
            while True:
                try:
                    fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        f.seek(0)
                        owner = f.read().strip() or "another process"
                        raise SceneBusyError(
                            f"scene '{scene_id}' in {self.root} is being written by another "
                            f"run ({owner}); wait for it to finish or stop it, then run "
                            f"again") from None
                    time.sleep(0.2)
            f.seek(0)
            f.truncate()
            f.write(f"pid {os.getpid()} on {socket.gethostname()} since {_now()}")
            f.flush()
            # the scene is ours now: temporary files a killed writer left are removed. They
            # live beside status.json and under _work/ (a version is built in a staging
            # folder), so the published versions' files are not walked: every scene of a
            # run is locked, complete ones too
            clean_stale_temps(d, recursive=False)
            if (d / "_work").is_dir():
                clean_stale_temps(d / "_work")
            try:
                yield
            finally:
                f.seek(0)
                f.truncate()
                f.flush()
                fcntl.flock(f.fileno(), fcntl.LOCK_UN)
        finally:
            f.close()

    # ---- stage checkpoints (resume within a scene)
    def _stage_record_path(self, scene_id: str, stage: str) -> Path:
        return self.work_dir(scene_id) / f"{stage}.done.json"

    def _read_stage_record(self, scene_id: str, stage: str) -> dict | None:
        p = self._stage_record_path(scene_id, stage)
        if not p.is_file():
            return None
        try:
            return json.loads(p.read_text())
        except json.JSONDecodeError as e:  # never happens with atomic writes; say so loudly
            raise StoreError(f"{scene_id}: stage checkpoint is not valid JSON: {p}: {e}") from e

    def stage_result(self, scene_id: str, stage: str) -> dict | None:
        """The result ``stage`` last recorded in its checkpoint (whatever its cache key), or
        None when it has none."""
        rec = self._read_stage_record(scene_id, stage)
        return None if rec is None else rec.get("result", {})

    def stage_done(self, scene_id: str, stage: str, key: str) -> dict | None:
        """The checkpoint record of ``stage`` if it completed with cache ``key``, else None."""
        rec = self._read_stage_record(scene_id, stage)
        if rec is None or rec.get("key") != key:
            return None
        for f in rec.get("files", []):
            if not (self.work_dir(scene_id) / f).exists():
                return None
        return rec

    def mark_stage_done(self, scene_id: str, stage: str, key: str, files: list[str],
                        result: dict | None = None, seconds: float | None = None) -> dict:
        rec = {"stage": stage, "key": key, "files": files, "result": result or {},
               "finished_at": _now()}
        if seconds is not None:
            rec["seconds"] = float(seconds)
        self.work_dir(scene_id, create=True)
        write_json_atomic(self._stage_record_path(scene_id, stage), rec)
        return rec

    # ---- publication (atomic version swap)
    def current_version_dir(self, scene_id: str) -> Path | None:
        cur = self.scene_dir(scene_id) / "CURRENT"
        if not cur.is_file():
            return None
        d = self.scene_dir(scene_id) / cur.read_text().strip()
        if not d.is_dir():
            raise StoreError(f"scene {scene_id}: CURRENT names a missing version folder {d}")
        return d

    @contextlib.contextmanager
    def publish(self, scene_id: str) -> Iterator[Path]:
        """Build a new version of a scene's outputs in a fresh folder; publish on success.

        Usage::

            with store.publish("fern") as out:
                write_parquet_atomic(out / "views.parquet", table) ...

        On an exception the half-built folder is deleted and the previous version stays.
        """
        sdir = self.scene_dir(scene_id)
        sdir.mkdir(parents=True, exist_ok=True)
        clean_stale_staging(sdir)
        staging = Path(tempfile.mkdtemp(prefix=f".staging-{_HOST}-{os.getpid()}-", dir=sdir))
        try:
            yield staging
            existing = sorted(p.name for p in sdir.glob("v[0-9][0-9][0-9][0-9]"))
            n = int(existing[-1][1:]) + 1 if existing else 1
            final = sdir / f"v{n:04d}"
            os.rename(staging, final)
            write_bytes_atomic(sdir / "CURRENT", final.name.encode())
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        # Old versions are garbage now; a reader that resolved CURRENT a moment ago may still
        # be reading one, so keep the previous version and drop older ones.
        for old in sorted(sdir.glob("v[0-9][0-9][0-9][0-9]"))[:-2]:
            shutil.rmtree(old, ignore_errors=True)

    # ---- readers
    def views(self, scene_id: str) -> pa.Table:
        d = self._require_version(scene_id)
        return pq.read_table(d / "views.parquet")

    def view_graph(self, scene_id: str) -> pa.Table:
        d = self._require_version(scene_id)
        return pq.read_table(d / "view_graph.parquet")

    def arrays(self, scene_id: str):
        """The scene's zarr group (read-only)."""
        import zarr

        d = self._require_version(scene_id)
        return zarr.open_group(str(d / "arrays.zarr"), mode="r")

    def _require_version(self, scene_id: str) -> Path:
        d = self.current_version_dir(scene_id)
        if d is None:
            raise StoreError(f"scene {scene_id!r} has no published outputs in {self.root}")
        return d


# --------------------------------------------------------------------------- staging
_HOST = HOST  # in staging folder names: .staging-<host>-<pid>-*
STALE_STAGING_SECONDS = 6 * 3600


def clean_stale_staging(scene_dir: Path, max_age: float = STALE_STAGING_SECONDS) -> list[str]:
    """Delete ``.staging-*`` folders left by a killed publish. Safe: a folder is removed only
    when its owner is known dead (named for this host and a pid that no longer exists) or,
    when the owner cannot be checked (another host, an older name), after ``max_age``
    seconds untouched. Returns the names removed."""
    removed = []
    for d in Path(scene_dir).glob(".staging-*"):
        parts = d.name.split("-")
        if writer_gone(d, parts[1:] if len(parts) >= 4 else [], max_age):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d.name)
    return removed


# --------------------------------------------------------------------------- tables
MANIFEST_FIRST = ["scene_id", "status", "error", "error_type", "source", "config_hash",
                  "engine_version", "version", "updated_at"]
# always present and always float64 (null where a scene has no value: a failed scene, a
# user's PLY, or no held-out view), so that readers can rely on the column and its type
MANIFEST_FLOAT = ("recon_seconds", "recon_train_psnr", "recon_test_psnr")


def _manifest_row(st: dict) -> dict:
    row = {k: st.get(k, "") for k in MANIFEST_FIRST}
    for k, v in sorted(st.get("counts", {}).items()):
        row[k if k.startswith("n_") else f"n_{k}"] = v
    total = 0.0
    for k, v in sorted(st.get("seconds", {}).items()):
        row[f"seconds_{k}"] = float(v)
        total += float(v)
    row["seconds_total"] = total
    for k, v in sorted(st.get("info", {}).items()):
        row[k] = json.dumps(v, sort_keys=True, default=_json_default) if isinstance(v, (dict, list)) else v
    return row


def _rows_to_table(rows: list[dict], first: list[str],
                   floats: tuple[str, ...] = ()) -> pa.Table:
    seen = dict.fromkeys(first)  # an ordered set: first the given, then as they appear
    for r in rows:
        seen.update(dict.fromkeys(r))
    seen.update(dict.fromkeys(floats))
    keys = list(seen)
    cols = {}
    for k in keys:
        vals = [r.get(k) for r in rows]
        if k in floats:
            cols[k] = pa.array([None if v in (None, "") else float(v) for v in vals],
                               pa.float64())
        else:
            cols[k] = _to_arrow_column(vals)
    if not rows:
        return pa.table({k: pa.array([], pa.float64() if k in floats else pa.string())
                         for k in keys})
    return pa.table(cols)


def _to_arrow_column(vals: list) -> pa.Array:
    present = [v for v in vals if v is not None and v != ""]
    if present and all(isinstance(v, bool) for v in present):
        return pa.array([None if v in (None, "") else bool(v) for v in vals], pa.bool_())
    if present and all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in present):
        return pa.array([None if v in (None, "") else int(v) for v in vals], pa.int64())
    if present and all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                       for v in present):
        return pa.array([None if v in (None, "") else float(v) for v in vals], pa.float64())
    return pa.array(["" if v is None else str(v) for v in vals], pa.string())


from freescale_core.store.objstore import (LEASE_SECONDS, _VERSION_RE,  # noqa: E402
                                           CommitConflictError, _etag, _mirror_root,
                                           _Precondition, filesystem, is_url, local_of,
                                           put_conditional)
import threading  # noqa: E402
import time  # noqa: E402


# --------------------------------------------------------------------------- object storage
class ObjectStore(Store):
    """A :class:`Store` whose objects live at ``self.url``; ``self.root`` is this process's
    local mirror (stage work, downloaded versions), never shared with another worker."""

    def __init__(self, url: str):
        self.url = url.rstrip("/")
        self.fs, self.base = filesystem(self.url)
        self.base = self.base.rstrip("/")
        self.root = _mirror_root(self.url)
        self.root.mkdir(parents=True, exist_ok=True)
        self._lease_lost: dict[str, str] = {}

    def __str__(self) -> str:
        return self.url

    def _r(self, *parts: str) -> str:
        return "/".join([self.base, *parts])

    def _cat(self, path: str) -> bytes | None:
        try:
            return self.fs.cat_file(path)
        except FileNotFoundError:
            return None

    def _put(self, path: str, data: bytes) -> None:
        self.fs.pipe_file(path, data)
        self.fs.invalidate_cache(path)

    # ---- store-level files (run_config.json, report.html)
    def read_file(self, name: str) -> bytes | None:
        return self._cat(self._r(name))

    def write_file(self, name: str, data: bytes) -> None:
        self._put(self._r(name), data)

    # ---- status and manifest
    def _status_infos(self) -> dict[str, dict]:
        """{scene id: object info of its status.json} in one recursive listing."""
        self.fs.invalidate_cache(self._r("scenes"))
        try:
            found = self.fs.find(self._r("scenes"), maxdepth=2, detail=True)
        except FileNotFoundError:
            return {}
        out = {}
        pre = self._r("scenes") + "/"
        for p, info in found.items():
            rel = p[len(pre):] if p.startswith(pre) else p
            parts = rel.split("/")
            if len(parts) == 2 and parts[1] == "status.json":
                out[parts[0]] = info
        return out

    def scene_ids(self) -> list[str]:
        return sorted(self._status_infos())

    def read_status(self, scene_id: str) -> dict:
        b = self._cat(self._r("scenes", scene_id, "status.json"))
        if b is None:
            return {}
        try:
            return json.loads(b)
        except json.JSONDecodeError as e:
            raise StoreError(f"status object is not valid JSON: "
                             f"{self.url}/scenes/{scene_id}/status.json: {e}") from e

    def _write_status(self, scene_id: str, st: dict) -> None:
        from freescale_core.files import _json_default

        self._put(self._r("scenes", scene_id, "status.json"),
                  json.dumps(st, indent=2, sort_keys=True, default=_json_default).encode())

    @staticmethod
    def _mtime(info: dict) -> float:
        t = info.get("LastModified") or info.get("mtime") or info.get("created") or 0
        return t.timestamp() if hasattr(t, "timestamp") else float(t)

    def manifest_stale(self) -> bool:
        infos = self._status_infos()
        try:
            m = self._mtime(self.fs.info(self._r("manifest.parquet")))
        except FileNotFoundError:
            return bool(infos)
        return any(self._mtime(i) >= m for i in infos.values())

    def _manifest_table(self) -> pa.Table:
        ids = sorted(self._status_infos())
        paths = [self._r("scenes", s, "status.json") for s in ids]
        blobs = self.fs.cat(paths) if paths else {}  # concurrent on async backends
        if isinstance(blobs, bytes):
            blobs = {paths[0]: blobs}
        rows = [_manifest_row(json.loads(blobs[p])) for p in paths
                if isinstance(blobs.get(p), bytes)]
        return _rows_to_table(rows, MANIFEST_FIRST, MANIFEST_FLOAT)

    def compile_manifest(self) -> None:
        import io

        table = self._manifest_table()
        buf = io.BytesIO()
        pq.write_table(table, buf)
        self._put(self._r("manifest.parquet"), buf.getvalue())

    def manifest(self) -> pa.Table:
        import io

        if self.manifest_stale():
            try:
                self.compile_manifest()
            except PermissionError:  # a read-only bucket: compile in memory
                return self._manifest_table()
        b = self._cat(self._r("manifest.parquet"))
        if b is None:
            return self._manifest_table()
        return pq.read_table(io.BytesIO(b))

    # ---- one writer per scene: a lease object
    @contextlib.contextmanager
    def scene_writer(self, scene_id: str, wait: float = 0.0) -> Iterator[None]:
        path = self._r("scenes", scene_id, ".writer.lease")
        token = uuid.uuid4().hex
        owner = f"pid {os.getpid()} on {socket.gethostname()} since {_now()}"

        def body() -> bytes:
            return json.dumps({"token": token, "owner": owner,
                               "expires": time.time() + LEASE_SECONDS}).encode()

        deadline = time.monotonic() + max(0.0, float(wait))
        while True:
            try:
                self._take_lease(path, body())
                break
            except _Precondition:
                cur = self._cat(path)
                info = json.loads(cur) if cur else {}
                if time.monotonic() >= deadline:
                    left = max(0.0, float(info.get("expires", 0)) - time.time())
                    raise SceneBusyError(
                        f"scene '{scene_id}' in {self.url} is being written by another run "
                        f"({info.get('owner', 'another process')}; its lease expires in "
                        f"{left:.0f} s unless renewed); wait for it to finish or stop it, "
                        f"then run again") from None
                time.sleep(0.2)
        if json.loads(self._cat(path) or b"{}").get("token") != token:  # lost a race
            raise SceneBusyError(f"scene '{scene_id}' in {self.url} is being written by "
                                 f"another run (its lease was taken first); run again later")
        stop = threading.Event()

        def renew():
            while not stop.wait(LEASE_SECONDS / 3):
                try:
                    etag = _etag(self.fs.info(path))
                    if json.loads(self._cat(path) or b"{}").get("token") != token:
                        self._lease_lost[scene_id] = "another run took the lease"
                        return
                    put_conditional(self.fs, path, body(), etag)
                except Exception as e:  # noqa: BLE001 - recorded; publish refuses
                    self._lease_lost[scene_id] = f"{type(e).__name__}: {e}"
                    return

        t = threading.Thread(target=renew, daemon=True, name=f"lease[{scene_id}]")
        t.start()
        try:
            yield
        finally:
            stop.set()
            t.join(timeout=5)
            with contextlib.suppress(Exception):
                if json.loads(self._cat(path) or b"{}").get("token") == token:
                    self.fs.rm_file(path)
            self._lease_lost.pop(scene_id, None)

    def _take_lease(self, path: str, data: bytes) -> None:
        try:
            put_conditional(self.fs, path, data, "*")
            return
        except _Precondition:
            pass
        cur = self._cat(path)
        try:
            info = json.loads(cur) if cur else {}
        except json.JSONDecodeError:
            info = {}
        if cur is not None and float(info.get("expires", 0)) < time.time():
            etag = _etag(self.fs.info(path))  # expired: take it over, once
            put_conditional(self.fs, path, data, etag)
            return
        raise _Precondition("held")

    # ---- stage checkpoints: local folder, mirrored as objects
    def _synced_path(self, scene_id: str) -> Path:
        return self.root / "scenes" / scene_id / ".synced.json"

    def work_dir(self, scene_id: str, create: bool = False) -> Path:
        """The local checkpoint folder, refreshed from the store's objects first (files of
        checkpoints another worker recorded)."""
        d = self.root / "scenes" / scene_id / "_work"
        d.mkdir(parents=True, exist_ok=True)
        self._pull_work(scene_id, d)
        return d

    def _pull_work(self, scene_id: str, d: Path) -> None:
        rdir = self._r("scenes", scene_id, "_work")
        self.fs.invalidate_cache(rdir)
        try:
            found = self.fs.find(rdir, detail=True)
        except FileNotFoundError:
            return
        sp = self._synced_path(scene_id)
        synced = json.loads(sp.read_text()) if sp.is_file() else {}
        changed = False
        for p, info in sorted(found.items()):
            rel = p[len(rdir) + 1:]
            tok = _etag(info)
            if synced.get(rel) == tok and (d / rel).exists():
                continue
            (d / rel).parent.mkdir(parents=True, exist_ok=True)
            tmp = d / rel.rsplit("/", 1)[0] / f".{Path(rel).name}.dl-{uuid.uuid4().hex[:8]}" \
                if "/" in rel else d / f".{rel}.dl-{uuid.uuid4().hex[:8]}"
            self.fs.get_file(p, str(tmp))
            os.replace(tmp, d / rel)
            synced[rel] = tok
            changed = True
        if changed:
            from freescale_core.files import write_json_atomic

            write_json_atomic(sp, synced)

    def mark_stage_done(self, scene_id: str, stage: str, key: str, files: list[str],
                        result: dict | None = None, seconds: float | None = None) -> dict:
        rec = Store.mark_stage_done(self, scene_id, stage, key, files, result, seconds)
        d = self.root / "scenes" / scene_id / "_work"
        rdir = self._r("scenes", scene_id, "_work")
        sp = self._synced_path(scene_id)
        synced = json.loads(sp.read_text()) if sp.is_file() else {}
        names = []
        for f in files:
            p = d / f
            names += ([str(q.relative_to(d)) for q in sorted(p.rglob("*")) if q.is_file()]
                      if p.is_dir() else [f])
        for rel in [*names, f"{stage}.done.json"]:  # the record last
            self.fs.put_file(str(d / rel), f"{rdir}/{rel}")
            self.fs.invalidate_cache(f"{rdir}/{rel}")
            synced[rel] = _etag(self.fs.info(f"{rdir}/{rel}"))
        from freescale_core.files import write_json_atomic

        write_json_atomic(sp, synced)
        return rec

    # ---- publication: unique prefix, then one conditional PUT of CURRENT
    def _current(self, scene_id: str) -> tuple[str | None, str | None]:
        """(version name CURRENT names, its ETag), (None, None) when none."""
        path = self._r("scenes", scene_id, "CURRENT")
        self.fs.invalidate_cache(path)
        try:
            info = self.fs.info(path)
        except FileNotFoundError:
            return None, None
        return self.fs.cat_file(path).decode().strip(), _etag(info)

    def current_version_dir(self, scene_id: str) -> Path | None:
        name, _ = self._current(scene_id)
        if name is None:
            return None
        local = self.root / "scenes" / scene_id / name
        if local.is_dir():
            return local
        rdir = self._r("scenes", scene_id, name)
        if not self.fs.exists(rdir):
            raise StoreError(f"scene {scene_id}: CURRENT names a missing version {self.url}/"
                             f"scenes/{scene_id}/{name}")
        tmp = local.with_name(f".dl-{name}-{uuid.uuid4().hex[:8]}")
        tmp.mkdir(parents=True)
        for p in self.fs.find(rdir):
            rel = p[len(rdir) + 1:]
            (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
            self.fs.get_file(p, str(tmp / rel))
        try:
            os.rename(tmp, local)
        except OSError:  # another thread of this process got it first
            shutil.rmtree(tmp, ignore_errors=True)
        return local

    def version_url(self, scene_id: str) -> str | None:
        name, _ = self._current(scene_id)
        return None if name is None else f"{self.url}/scenes/{scene_id}/{name}"

    @contextlib.contextmanager
    def publish(self, scene_id: str) -> Iterator[Path]:
        """Build a version in a local staging folder; on success upload it under a fresh
        prefix and make it visible with one conditional PUT of ``CURRENT``."""
        sdir = self.root / "scenes" / scene_id
        sdir.mkdir(parents=True, exist_ok=True)
        prev, prev_etag = self._current(scene_id)
        staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=sdir))
        try:
            yield staging
            rs = self._r("scenes", scene_id)
            self.fs.invalidate_cache(rs)
            try:
                existing = sorted(Path(p).name[:5] for p in self.fs.glob(f"{rs}/{_VERSION_RE}*"))
            except FileNotFoundError:
                existing = []
            n = int(existing[-1][1:]) + 1 if existing else 1
            name = f"v{n:04d}-{uuid.uuid4().hex[:8]}"
            for p in sorted(staging.rglob("*")):
                if p.is_file():
                    self.fs.put_file(str(p), f"{rs}/{name}/{p.relative_to(staging).as_posix()}")
            lost = self._lease_lost.get(scene_id)
            if lost:
                raise CommitConflictError(
                    f"scene '{scene_id}' in {self.url}: this run lost its writer lease "
                    f"({lost}); its version {name} was uploaded but not made visible")
            try:
                put_conditional(self.fs, f"{rs}/CURRENT", name.encode(),
                                "*" if prev is None else prev_etag)
            except _Precondition:
                now, _ = self._current(scene_id)
                raise CommitConflictError(
                    f"scene '{scene_id}' in {self.url}: another writer published {now} while "
                    f"this run was writing (it started from {prev or 'no version'}); this "
                    f"run's version {name} stays invisible and {now} is kept") from None
            os.rename(staging, sdir / name)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        # keep the previous version (a reader may be reading it), drop older ones
        try:
            olds = sorted(self.fs.glob(f"{rs}/{_VERSION_RE}*"), key=lambda p: Path(p).name)
        except FileNotFoundError:
            olds = []
        keep = {name, prev}
        for p in [q for q in olds if Path(q).name not in keep][:-1] if len(olds) > 2 else []:
            with contextlib.suppress(Exception):
                self.fs.rm(p, recursive=True)

    # ---- readers: parquet through pyarrow's filesystem layer, zarr through fsspec
    def _pa_fs(self):
        from pyarrow.fs import FSSpecHandler, PyFileSystem

        return PyFileSystem(FSSpecHandler(self.fs))

    def _version_path(self, scene_id: str) -> str:
        name, _ = self._current(scene_id)
        if name is None:
            raise StoreError(f"scene {scene_id!r} has no published outputs in {self.url}")
        return self._r("scenes", scene_id, name)

    def views(self, scene_id: str) -> pa.Table:
        return pq.read_table(f"{self._version_path(scene_id)}/views.parquet",
                             filesystem=self._pa_fs())

    def view_graph(self, scene_id: str) -> pa.Table:
        return pq.read_table(f"{self._version_path(scene_id)}/view_graph.parquet",
                             filesystem=self._pa_fs())

    def arrays(self, scene_id: str):
        import zarr
        from zarr.storage import FsspecStore

        url = f"{self.url.split('://')[0]}://{self._version_path(scene_id)}/arrays.zarr"
        return zarr.open_group(FsspecStore.from_url(url, read_only=True), mode="r")


def read_store_file(store: str | Path, name: str) -> bytes | None:
    """A store-level file (``run_config.json``, ...) of a local or URL store, None if absent."""
    if is_url(store):
        return Store(store).read_file(name)
    p = Path(local_of(store)) / name
    return p.read_bytes() if p.is_file() else None


def write_store_file(store: str | Path, name: str, data: bytes) -> str:
    """Write a store-level file; returns where it went."""
    if is_url(store):
        Store(store).write_file(name, data)
        return f"{str(store).rstrip('/')}/{name}"
    from freescale_core.files import write_bytes_atomic

    p = Path(local_of(store)) / name
    write_bytes_atomic(p, data)
    return str(p)
