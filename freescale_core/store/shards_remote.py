"""Training shards on object storage (``s3://bucket/shards``, any fsspec URL): packing into a
bucket, listing and verifying it, and the bounded local cache the shard datasets read
through.

Packing (:class:`UrlShardsOut`, used by :func:`freescale_core.store.shards.pack`): each
shard is built in a local temporary folder exactly as for a local OUT and hashed, then
uploaded as one object, an uncompressed zip of that folder (its chunks are compressed
already), under a name of its own, ``shards/000003-1f2e3d4c.zarr.zip`` (number and a random
token, so no two packs ever write one object); the manifest is PUT last, one object, so a reader
sees the previous complete manifest or the new one and never a shard set half written. The
manifest PUT is conditional on the manifest this pack last saw (S3 ``If-Match`` /
``If-None-Match: *``) and one pack at a time holds a lease object ``OUT/.pack.lease``
(expiry, renewed while packing), so of two packers into one OUT the second stops at once
naming the first. Shard objects no manifest row names (a killed pack's upload, superseded shards)
are ignored by readers and deleted by the next pack.

Reading (:class:`ShardCache`): a shard is fetched whole (one GET) and unpacked into a local
cache folder, hashed against the manifest's ``shard_sha256`` on the fetched bytes (the same
checksum as the local folder's) (a corrupt or missing object fails in one line naming
the shard) and renamed into place; then read by zarr like a local shard. The cache holds at
most ``max_bytes`` of shard files (counted from the manifest's ``shard_bytes`` before a
fetch starts, so never over the bound, downloads in flight included); the least recently
used shard that is neither being read nor next in line is evicted first. A background
thread per process fetches the next ``prefetch`` shards of the reading order while the
current one is read (the iterable dataset gives its order; the map-style one fetches on
demand). Entries are named by their SHA-256, so a re-packed shard never reuses a stale copy;
entries found on disk from an earlier run are re-hashed on first use in a process, as the
local reader hashes a local shard.
"""

from __future__ import annotations

import collections
import contextlib
import fcntl
import hashlib
import io
import json
import os
import re
import shutil
import socket
import tempfile
import threading
import time
import uuid
import zipfile
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from freescale_core.errors import StoreError
from freescale_core.store.objstore import _etag, _Precondition, filesystem, put_conditional

LEASE_SECONDS = float(os.environ.get("FREESCALE_LEASE_SECONDS", 120))
_URL_SHARD = re.compile(r"[0-9]{6}-[0-9a-f]{8}\.zarr\.zip")
_ENTRY = re.compile(r"[0-9a-f]{20}")


def _split(url: str) -> tuple[object, str, str]:
    url = url.rstrip("/")
    fs, base = filesystem(url)
    return fs, base.rstrip("/"), url


def read_url_manifest(url: str) -> pa.Table:
    """The shard manifest at ``url/manifest.parquet`` (FileNotFoundError when absent)."""
    fs, base, url = _split(url)
    try:
        data = fs.cat_file(f"{base}/manifest.parquet")
    except FileNotFoundError:
        raise FileNotFoundError(f"no shard manifest at {url}/manifest.parquet (run "
                                f"`freescale shards pack STORE {url}`)") from None
    return pq.read_table(io.BytesIO(data))


def files_bytes_and_sha(files) -> tuple[int, str]:
    """``(total bytes, shard SHA-256)`` of ``(relative posix path, bytes)`` pairs given in
    path-part order (``sorted(..., key=lambda r: r.split("/"))``): SHA-256 over each path
    and the SHA-256 of its content, the checksum the manifest records."""
    h = hashlib.sha256()
    total = 0
    for rel, data in files:
        total += len(data)
        h.update(rel.encode())
        h.update(hashlib.sha256(data).digest())
    return total, h.hexdigest()


def _dir_bytes_and_sha(d: Path) -> tuple[int, str]:
    """:func:`files_bytes_and_sha` of the shard folder ``d`` (the manifest's checksum)."""
    return files_bytes_and_sha(
        (p.relative_to(d).as_posix(), p.read_bytes())
        for p in sorted(q for q in Path(d).rglob("*") if q.is_file()))


def _sorted(rels) -> list[str]:
    """Relative paths in path-part order (the order the checksum uses)."""
    return sorted(rels, key=lambda r: r.split("/"))


def zip_shard(d: Path) -> bytes:
    """The shard folder ``d`` as one uncompressed zip (its chunks are compressed already),
    members in checksum order."""
    buf = io.BytesIO()
    files = {p.relative_to(d).as_posix(): p for p in d.rglob("*") if p.is_file()}
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as z:
        for rel in _sorted(files):
            z.writestr(zipfile.ZipInfo(rel, (1980, 1, 1, 0, 0, 0)), files[rel].read_bytes())
    return buf.getvalue()


def fetch_shard(fs, base: str, url: str, shard_path: str, sha256: str) -> dict[str, bytes]:
    """Every file of shard ``shard_path`` (one zip object) as ``{relative path: bytes}``,
    checked against the manifest's ``sha256``. Raises :class:`StoreError` naming the shard
    when it is missing, unreadable or its bytes do not match."""
    where = f"{url}/{shard_path}"
    try:
        data = fs.cat_file(f"{base}/{shard_path}")
    except FileNotFoundError:
        raise StoreError(f"shard {where} named by {url}/manifest.parquet is missing") from None
    bad = (f"shard {where} does not match its SHA-256 in {url}/manifest.parquet (the object "
           f"was changed or truncated): re-pack it with `freescale shards pack`; "
           f"`freescale shards verify {url}` checks all")
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            files = {r: z.read(r) for r in _sorted(n for n in z.namelist()
                                                   if not n.endswith("/"))}
    except Exception:  # noqa: BLE001 - a bad CRC, a truncated or mangled zip: named
        raise StoreError(bad) from None
    if files_bytes_and_sha(files.items())[1] != sha256:
        raise StoreError(bad)
    return files


def verify_url(url: str) -> list[str]:
    """The shards of the manifest at ``url`` whose objects do not hash to the manifest."""
    fs, base, url = _split(url)
    bad = []
    for r in {r["shard"]: r for r in read_url_manifest(url).to_pylist()}.values():
        try:
            fetch_shard(fs, base, url, r["shard_path"], r["shard_sha256"])
        except StoreError:
            bad.append(r["shard"])
    return bad


# --------------------------------------------------------------------------- packing
@contextlib.contextmanager
def _lease(fs, path: str, url: str):
    """One packer per OUT: a lease object created with ``If-None-Match: *``, renewed every
    third of its life, taken over only when expired."""
    token = uuid.uuid4().hex
    owner = f"pid {os.getpid()} on {socket.gethostname()}"

    def body() -> bytes:
        return json.dumps({"token": token, "owner": owner,
                           "expires": time.time() + LEASE_SECONDS}).encode()

    try:
        put_conditional(fs, path, body(), "*")
    except _Precondition:
        try:
            info = json.loads(fs.cat_file(path))
        except (FileNotFoundError, ValueError):
            info = {}
        if float(info.get("expires", 0)) >= time.time():
            raise StoreError(f"{url} is being packed by another run ({info.get('owner', '?')}, "
                             f"lease expires in {info['expires'] - time.time():.0f} s); wait "
                             f"for it to finish") from None
        try:
            put_conditional(fs, path, body(), _etag(fs.info(path)))
        except _Precondition:
            raise StoreError(f"{url} is being packed by another run (it took the expired "
                             f"lease first)") from None
    stop = threading.Event()

    def renew():
        while not stop.wait(LEASE_SECONDS / 3):
            with contextlib.suppress(Exception):
                put_conditional(fs, path, body(), _etag(fs.info(path)))

    t = threading.Thread(target=renew, daemon=True, name="pack-lease")
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join(timeout=5)
        with contextlib.suppress(Exception):
            if json.loads(fs.cat_file(path)).get("token") == token:
                fs.rm_file(path)


class UrlShardsOut:
    """Where ``pack`` commits on object storage (see the module doc)."""

    def __init__(self, url: str):
        self.fs, self.base, self.out = _split(url)
        self._etag: str | None = None
        self._tmp: Path | None = None

    def __str__(self) -> str:
        return self.out

    @contextlib.contextmanager
    def lock(self):
        with _lease(self.fs, f"{self.base}/.pack.lease", self.out):
            self._tmp = Path(tempfile.mkdtemp(prefix="freescale-pack-"))  # shards built here
            try:
                yield
            finally:
                shutil.rmtree(self._tmp, ignore_errors=True)

    def prepare(self) -> None:
        pass

    def manifest(self) -> pa.Table | None:
        p = f"{self.base}/manifest.parquet"
        self.fs.invalidate_cache(p)
        try:
            info = self.fs.info(p)
        except FileNotFoundError:
            self._etag = None
            return None
        self._etag = _etag(info)
        return pq.read_table(io.BytesIO(self.fs.cat_file(p)))

    def staging(self) -> Path:
        return self._tmp / f".tmp-{uuid.uuid4().hex[:8]}"

    def _names(self) -> list[str]:
        d = f"{self.base}/shards"
        self.fs.invalidate_cache(d)
        try:
            return [Path(p).name for p in self.fs.ls(d, detail=False)]
        except FileNotFoundError:
            return []

    def commit_shard(self, tmp: Path) -> tuple[str, str]:
        nums = [int(n[:6]) for n in self._names() if n[:6].isdigit()]
        name = f"{max(nums, default=-1) + 1:06d}"
        shard_path = f"shards/{name}-{uuid.uuid4().hex[:8]}.zarr.zip"
        self.upload(zip_shard(tmp), f"{self.base}/{shard_path}")
        return name, shard_path

    def upload(self, data: bytes, remote: str) -> None:
        """One PUT of the shard's zip (a test replaces it to die around it)."""
        self.fs.pipe_file(remote, data)

    def write_manifest(self, table: pa.Table) -> None:
        buf = io.BytesIO()
        pq.write_table(table, buf)
        p = f"{self.base}/manifest.parquet"
        try:
            put_conditional(self.fs, p, buf.getvalue(), self._etag or "*")
        except _Precondition:
            raise StoreError(f"{self.out}/manifest.parquet was changed by another run while "
                             f"this one packed; the shards it uploaded are not listed (the "
                             f"next pack deletes them): pack again") from None
        self.fs.invalidate_cache(p)
        self._etag = _etag(self.fs.info(p))

    def gc(self, rows: list[dict]) -> None:
        live = {Path(r["shard_path"]).name for r in rows}
        for n in self._names():
            if _URL_SHARD.fullmatch(n) and n not in live:
                with contextlib.suppress(FileNotFoundError):
                    self.fs.rm_file(f"{self.base}/shards/{n}")


# --------------------------------------------------------------------------- the cache
def default_cache_dir() -> Path:
    return Path(tempfile.gettempdir()) / "freescale-shard-cache"


_CACHES: dict[tuple[int, str], "ShardCache"] = {}  # (pid, folder): one cache per folder


def shared_cache(url: str, shards: dict[str, tuple[str, int]], max_bytes: int, root: Path,
                 prefetch: int = 2) -> "ShardCache":
    """The process's :class:`ShardCache` on folder ``root``: readers of one process that
    name the same folder share one cache (one bound, one accounting)."""
    key = (os.getpid(), str(root))
    c = _CACHES.get(key)
    if c is None or c.closed:
        c = _CACHES[key] = ShardCache(url, shards, max_bytes, root, prefetch)
    else:
        c.adopt(shards, max_bytes, prefetch)
    return c


def close_caches() -> None:
    """Release every cache folder this process holds (a new reader starts from disk)."""
    for k, c in list(_CACHES.items()):
        if k[0] == os.getpid():
            c.close()
        _CACHES.pop(k, None)


class ShardCache:
    """Local copies of the shards of the manifest at ``url``, at most ``max_bytes`` of shard
    files, least recently used evicted first; a background thread fetches the next
    ``prefetch`` shards of :meth:`plan` (see the module doc).

    Args:
        url: shards URL.
        shards: ``{shard_path: (shard_sha256, shard_bytes)}`` from the manifest.
        max_bytes: bound on the bytes of the cached shard files (>= the largest shard).
        root: this process's cache folder (one reader process per folder: it is locked).
        prefetch: shards fetched ahead of the one being read (0: none).
    """

    def __init__(self, url: str, shards: dict[str, tuple[str, int]], max_bytes: int,
                 root: Path, prefetch: int = 2):
        self.fs, self.base, self.url = _split(url)
        self.shards = shards
        self.max_bytes = int(max_bytes)
        self.prefetch = max(0, int(prefetch))
        big = max(shards.items(), key=lambda kv: kv[1][1], default=None)
        if big is not None and big[1][1] > self.max_bytes:
            raise StoreError(f"shard cache of {self.max_bytes / 2**20:.1f} MB is smaller than "
                             f"shard {self.url}/{big[0]} ({big[1][1] / 2**20:.1f} MB): raise "
                             f"cache_bytes (per DataLoader worker it is cache_bytes / "
                             f"num_workers)")
        self.root = self._claim(Path(root))
        self.cond = threading.Condition()
        self.have: collections.OrderedDict[str, int] = collections.OrderedDict()  # LRU first
        self.inflight: dict[str, int] = {}
        self.errors: dict[str, BaseException] = {}
        self.unverified: set[str] = set()
        self.current: str | None = None
        self.order: list[str] = []
        self.pos = 0
        self.fetched_bytes = 0
        self.fetches = 0
        self._thread: threading.Thread | None = None
        self.closed = False
        self._scan()

    def adopt(self, shards: dict[str, tuple[str, int]], max_bytes: int, prefetch: int) -> None:
        """Another reader of this process on the same folder: its shards join, its bound
        and prefetch apply from now on."""
        with self.cond:
            self.shards.update(shards)
            self.max_bytes, self.prefetch = int(max_bytes), max(0, int(prefetch))
            while self._used() > self.max_bytes and any(k != self.current for k in self.have):
                self._evict(next(k for k in self.have if k != self.current))

    def close(self) -> None:
        """Stop prefetching and release the folder's lock (the files stay: a warm cache)."""
        with self.cond:
            self.closed = True
            self.cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=10)
        with contextlib.suppress(Exception):
            self._lockfile.close()

    # ---- the folder
    def _claim(self, root: Path) -> Path:
        for d in (root, root.with_name(f"{root.name}-p{os.getpid()}")):
            d.mkdir(parents=True, exist_ok=True)
            f = open(d / ".lock", "a+")
            try:
                fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                f.close()
                continue
            self._lockfile = f  # held for the life of the process
            return d
        raise StoreError(f"shard cache folders {root}* are in use by other processes")

    def _scan(self) -> None:
        found = []
        for d in self.root.iterdir():
            if d.name.startswith(".tmp-"):
                shutil.rmtree(d, ignore_errors=True)
            elif d.is_dir() and _ENTRY.fullmatch(d.name):
                n = sum(p.stat().st_size for p in d.rglob("*") if p.is_file())
                found.append((d.stat().st_mtime, d.name, n))
        for _, k, n in sorted(found):
            self.have[k] = n
            self.unverified.add(k)
        while self._used() > self.max_bytes and self.have:
            self._evict(next(iter(self.have)))

    @staticmethod
    def key(sha256: str) -> str:
        return sha256[:20]

    def _used(self) -> int:
        return sum(self.have.values()) + sum(self.inflight.values())

    def _evict(self, k: str) -> None:
        self.have.pop(k, None)
        self.unverified.discard(k)
        shutil.rmtree(self.root / k, ignore_errors=True)

    def _upcoming(self) -> list[str]:
        nxt = self.order[self.pos + 1:self.pos + 1 + self.prefetch]
        return [self.key(self.shards[s][0]) for s in nxt]

    def _make_room(self, n: int, keep: set[str], wait: bool) -> bool:
        """Evict until ``n`` more bytes fit; entries in ``keep`` only when ``wait`` (the
        shard being read needs the room) and nothing else is left. Caller holds the lock."""
        while self._used() + n > self.max_bytes:
            free = [k for k in self.have if k not in keep and k != self.current]
            if not free and wait:
                free = [k for k in reversed(self._upcoming()) if k in self.have
                        and k != self.current]
            if free:
                self._evict(free[0])
            elif wait and self.inflight:
                self.cond.wait(0.5)
            else:
                return False
        return True

    # ---- reading
    def plan(self, shard_paths: list[str]) -> None:
        """The order this process will read shards in (prefetch follows it)."""
        with self.cond:
            self.order = [s for i, s in enumerate(shard_paths)
                          if i == 0 or s != shard_paths[i - 1]]
            self.pos = 0
            self.cond.notify_all()
        with self.cond:
            if self.prefetch and len(self.order) > 1 and (
                    self._thread is None or not self._thread.is_alive()):
                self._thread = threading.Thread(target=self._prefetch_loop, daemon=True,
                                                name="shard-prefetch")
                self._thread.start()

    def get(self, shard_path: str) -> Path:
        """The local folder of ``shard_path``, fetched (and checked) first when absent."""
        sha, n = self.shards[shard_path]
        k = self.key(sha)
        with self.cond:
            self.current = k
            if self.pos + 1 < len(self.order) and self.order[self.pos] != shard_path:
                try:
                    self.pos = self.order.index(shard_path, self.pos)
                    self.cond.notify_all()
                except ValueError:
                    pass
            while True:
                if k in self.have:
                    self.have.move_to_end(k)
                    if k not in self.unverified:
                        return self.root / k
                    break
                if k in self.errors:
                    raise self.errors.pop(k)
                if k in self.inflight:
                    self.cond.wait(0.5)
                    continue
                if not self._make_room(n, set(), wait=True):
                    raise StoreError(f"shard cache of {self.max_bytes / 2**20:.1f} MB cannot "
                                     f"hold shard {self.url}/{shard_path} ({n / 2**20:.1f} "
                                     f"MB): raise cache_bytes")
                self.inflight[k] = n
                break
        if k in self.unverified:  # from an earlier run: hashed once here, as a local shard
            ok = _dir_bytes_and_sha(self.root / k)[1] == sha
            with self.cond:
                self.unverified.discard(k)
                if ok:
                    return self.root / k
                self._evict(k)
                self.inflight[k] = n
        self._fetch(k, shard_path)
        return self.root / k

    def _fetch(self, k: str, shard_path: str) -> None:
        """Download into a temporary folder and rename it into place; the reservation of
        ``inflight[k]`` is released either way. Errors propagate to the caller."""
        sha, n = self.shards[shard_path]
        tmp = self.root / f".tmp-{uuid.uuid4().hex[:8]}"
        try:
            files = fetch_shard(self.fs, self.base, self.url, shard_path, sha)
            for rel, data in files.items():
                p = tmp / rel
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_bytes(data)
            os.rename(tmp, self.root / k)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            with self.cond:
                self.inflight.pop(k, None)
                self.cond.notify_all()
            raise
        with self.cond:
            self.inflight.pop(k, None)
            self.have[k] = n
            self.fetched_bytes += n
            self.fetches += 1
            self.cond.notify_all()

    def _prefetch_loop(self) -> None:
        """Fetch the next shards of the plan; ends when the plan's last shard is being read
        (a new :meth:`plan` starts it again) or the cache is closed."""
        while True:
            with self.cond:
                if self.closed or self.pos + 1 >= len(self.order):
                    return
                up = self._upcoming()
                todo = None
                for s in self.order[self.pos + 1:self.pos + 1 + self.prefetch]:
                    k = self.key(self.shards[s][0])
                    if k not in self.have and k not in self.inflight and k not in self.errors:
                        todo = (k, s)
                        break
                if todo is None or not self._make_room(
                        self.shards[todo[1]][1], set(up), wait=False):
                    self.cond.wait(0.5)
                    continue
                self.inflight[todo[0]] = self.shards[todo[1]][1]
            try:
                self._fetch(*todo)
            except BaseException as e:  # noqa: BLE001 - raised where the shard is read
                with self.cond:
                    self.errors[todo[0]] = e
                    self.cond.notify_all()

    def stats(self) -> dict:
        with self.cond:
            return {"cached_bytes": sum(self.have.values()), "max_bytes": self.max_bytes,
                    "fetched_bytes": self.fetched_bytes, "fetches": self.fetches,
                    "in_flight": len(self.inflight)}
