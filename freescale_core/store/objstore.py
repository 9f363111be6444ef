"""The store on object storage (``s3://``, ``gs://``, any fsspec URL): same layout, same API
as :class:`~freescale_core.store.store.Store`, a commit protocol without ``rename``.

``Store("s3://bucket/store")`` returns an :class:`ObjectStore`. Stages still compute into a
local folder (a per-process mirror, never shared: workers need no common folder); what other
workers or a later run must see is put as objects:

* ``scenes/<id>/status.json`` and ``scenes/<id>/_work/<stage>.done.json`` (+ the files the
  checkpoint lists; the record last, so a killed upload leaves no checkpoint);
* a version is uploaded under its own unique prefix ``scenes/<id>/v0003-<token>/`` and then
  made visible by one PUT of ``scenes/<id>/CURRENT`` naming it. The PUT is conditional
  (``If-Match`` the ``CURRENT`` this writer started from, ``If-None-Match: *`` when there
  was none) where the backend has conditional writes (S3), so of two writers of one scene
  exactly one wins and the other gets :class:`CommitConflictError`;
* one writer per scene: a lease object ``scenes/<id>/.writer.lease`` with an expiry, created
  with ``If-None-Match: *`` (read back and checked where the backend has no conditional
  write), renewed while the run holds it, taken over only when expired.

Credentials and the endpoint come from the filesystem library's own environment / config
(``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ``~/.aws``, ...), never from arguments.
Parquet is read through pyarrow's filesystem layer and zarr through zarr's fsspec store.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import socket
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any, Iterator

import pyarrow as pa
import pyarrow.parquet as pq

from freescale_core.errors import StoreError
from freescale_core.store.store import Store

LEASE_SECONDS = float(os.environ.get("FREESCALE_LEASE_SECONDS", 120))
_VERSION_RE = "v[0-9][0-9][0-9][0-9]"


class CommitConflictError(StoreError):
    """Another writer made a version of the scene visible first (the conditional ``CURRENT``
    write failed); the version this writer uploaded stays invisible."""


def is_url(s: Any) -> bool:  # (also in store.py, which must not import this module)
    """A store given as a URL of an object store (``file://`` is a local folder)."""
    return isinstance(s, str) and "://" in s and not s.startswith("file://")


def local_of(s: str | Path) -> str | Path:
    """``file:///a/b`` -> ``/a/b``; anything else unchanged."""
    return s[len("file://"):] if isinstance(s, str) and s.startswith("file://") else s


def filesystem(url: str):
    """``(fsspec filesystem, path without scheme)`` for ``url``; the library reads its own
    credentials and endpoint from the environment."""
    import fsspec

    try:
        return fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as e:
        raise StoreError(f"cannot open {url}: {e}") from None


def _is_missing(e: BaseException) -> bool:
    return isinstance(e, FileNotFoundError)


def _mirror_root(url: str) -> Path:
    base = Path(os.environ.get("FREESCALE_MIRROR_DIR") or tempfile.gettempdir())
    h = hashlib.sha256(url.encode()).hexdigest()[:12]
    return base / "freescale-mirror" / f"{h}-{socket.gethostname()}-{os.getpid()}"


# --------------------------------------------------------------------------- conditional put
class _Precondition(Exception):
    pass


def _etag(info: dict) -> str:
    for k in ("ETag", "etag", "md5Hash", "generation"):
        if info.get(k):
            return str(info[k]).strip('"')
    return f"{info.get('size')}-{info.get('LastModified') or info.get('mtime') or info.get('created')}"


def put_conditional(fs, path: str, data: bytes, match: str | None) -> None:
    """PUT ``data`` at ``path`` only if the object is absent (``match == "*"``) or still has
    ETag ``match``. Raises :class:`_Precondition` otherwise. S3: one conditional PUT
    (``If-None-Match`` / ``If-Match``); other backends: check, write, read back (a race
    inside that window is caught by the read-back of the lease token)."""
    if type(fs).__name__ == "S3FileSystem":
        bucket, key, _ = fs.split_path(path)
        kw = {"IfNoneMatch": "*"} if match == "*" else {"IfMatch": f'"{match}"'}
        try:
            fs.call_s3("put_object", Bucket=bucket, Key=key, Body=data, **kw)
        except Exception as e:  # noqa: BLE001 - botocore's ClientError via s3fs
            text = f"{type(e).__name__} {e}"
            if "PreconditionFailed" in text or "412" in text or "ConditionalRequestConflict" in text \
                    or isinstance(e, FileExistsError):
                raise _Precondition(text) from None
            raise
        fs.invalidate_cache(path)
        return
    try:
        cur = _etag(fs.info(path))
    except FileNotFoundError:
        cur = None
    if (match == "*" and cur is not None) or (match != "*" and cur != match):
        raise _Precondition(f"{path}: etag {cur} != {match}")
    fs.pipe_file(path, data)
    fs.invalidate_cache(path)


# --------------------------------------------------------------------------- the store
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
        from freescale_core.store.store import MANIFEST_FIRST, MANIFEST_FLOAT, _manifest_row, \
            _rows_to_table

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
        from freescale_core.store.store import SceneBusyError, _now

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
