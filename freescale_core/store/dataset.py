"""PyTorch datasets over training shards (``freescale shards pack``), with pluggable view
samplers.

A sample is one scene's ``V = n_input + n_target`` views, chosen by a view sampler::

    {"images":         [V, 3, R, R] float32 in [0, 1]   inputs first, then targets
     "fxfycxcy":       [V, 4] float32 pixels of the R x R images
     "world_from_cam": [V, 4, 4] float32 OpenCV camera-to-world
     "is_free":        [V] bool
     "view_id":        [V] int64 views.parquet ids in the source store version
     "frame_index":    [V] int64 capture order (-1 for free views)
     "target_weight":  [n_target] float32
     "n_input":        int
     "scene_id":       str}

Every tensor has a fixed size, so the default ``collate_fn`` batches them. Determinism: the
views of sample ``i`` are drawn with ``np.random.default_rng([seed, epoch, i])`` (map-style)
or ``[seed, epoch, scene_entry, k]`` (iterable), independent of ``num_workers``. Workers open
their own zarr readers (the readers are created lazily in the process that reads, never
pickled).

Sampler protocol: any object with ``sample(scene: SceneViews, rng: np.random.Generator)``
returning an object with ``.input_ids``, ``.target_ids`` (view rows ``0..N-1`` of the scene)
and ``.target_weight``. :class:`RandomViewSampler` is the default;
``freescale_core.downstream.lvsm.sampler.ViewSampler`` (frame-distance + view-graph branches,
curriculum) plugs in unchanged: ``ShardDataset(out, sampler=ViewSampler())``.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from freescale_core.errors import StoreError


# The sampler's input record has one definition, next to the LVSM sampler that defined it:
# scene_id, is_free [N], frame_index [N] (capture order, -1 free), edges (src, dst, wiou).
from freescale_core.store.scene_views import SceneViews  # noqa: E402


@dataclass
class ViewSample:
    input_ids: np.ndarray    # [n_input] int64 rows of the scene
    target_ids: np.ndarray   # [n_target] int64
    target_weight: np.ndarray  # [n_target] float32


class ViewSampler(Protocol):
    def sample(self, scene: SceneViews, rng: np.random.Generator): ...


@dataclass
class RandomViewSampler:
    """Uniformly random distinct views (with replacement only when the scene is too small).

    Attributes:
        n_input, n_target: views per sample.
        free_targets_only: draw targets among free views when the scene has enough of them.
    """

    n_input: int = 4
    n_target: int = 2
    free_targets_only: bool = False

    def sample(self, scene: SceneViews, rng: np.random.Generator) -> ViewSample:
        n = scene.n_views
        k = self.n_input + self.n_target
        if self.free_targets_only and int(scene.is_free.sum()) >= self.n_target:
            free = np.flatnonzero(scene.is_free)
            tgt = rng.choice(free, self.n_target, replace=False)
            rest = np.setdiff1d(np.arange(n), tgt)
            inp = rng.choice(rest, self.n_input, replace=len(rest) < self.n_input)
        else:
            ids = rng.choice(n, k, replace=n < k)
            inp, tgt = ids[: self.n_input], ids[self.n_input:]
        return ViewSample(np.asarray(inp, np.int64), np.asarray(tgt, np.int64),
                          np.ones(self.n_target, np.float32))


# --------------------------------------------------------------------------- shard reader
# (shard folder, manifest SHA-256) pairs whose bytes this process has checked
_VERIFIED: set[tuple[str, str]] = set()


def check_shard(p: Path, sha256: str, manifest: Path) -> None:
    """Raise :class:`StoreError` naming the shard when its files do not hash to the
    manifest's ``shard_sha256`` (a flipped byte, a truncated or deleted chunk); once per
    shard and process (a forked worker inherits what its parent checked)."""
    key = (str(p), sha256)
    if key in _VERIFIED:
        return
    from freescale_core.store.shards import shard_sha256

    if shard_sha256(p) != sha256:
        raise StoreError(f"shard {p} does not match its SHA-256 in {manifest} (a file was "
                         f"changed, truncated or deleted): re-pack it with `freescale shards "
                         f"pack` into a fresh folder; `freescale shards verify` checks all")
    _VERIFIED.add(key)


class ShardReader:
    """Reads the scenes listed in a shard manifest, in a folder or at a URL
    (``s3://bucket/shards``). Zarr groups are opened lazily and per process, so one reader
    can be shared by (pickled into) DataLoader workers. Each shard's bytes are checked
    against the manifest's SHA-256 before its first read in a process (``verify=False``
    skips the check for a local folder; a chunk that cannot be decoded still fails naming
    the shard).

    From a URL, shards are fetched whole into a bounded local cache
    (:class:`~freescale_core.store.shards_remote.ShardCache`, always hashed on the fetched
    bytes): ``cache_bytes`` is the bound for the reader's process, divided evenly among
    DataLoader workers (each worker has its own folder under ``cache_dir``), and
    ``prefetch`` shards of the reading order are fetched ahead by a background thread.
    """

    def __init__(self, out: str | Path, scenes: list[str] | None = None, verify: bool = True,
                 cache_bytes: int = 2 * 2**30, cache_dir: str | Path | None = None,
                 prefetch: int = 2):
        from freescale_core.store.objstore import is_url, local_of
        from freescale_core.store.shards import read_manifest

        self.url = str(out).rstrip("/") if is_url(out) else None
        self.out = self.url if self.url else Path(local_of(out))
        rows = read_manifest(self.out).to_pylist()
        if scenes is not None:
            missing = set(scenes) - {r["scene_id"] for r in rows}
            if missing:
                raise StoreError(f"scenes {sorted(missing)} are not in the shards at {out}")
            rows = [r for r in rows if r["scene_id"] in set(scenes)]
        # shard order, then position in the shard: neighbouring entries share a shard
        self.entries = sorted(rows, key=lambda r: (r["shard"], r["view_start"]))
        self.cache_bytes, self.prefetch = int(cache_bytes), int(prefetch)
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self._groups: dict = {}
        self._meta: dict = {}
        self._images: dict = {}
        self._pid = None
        self._cache = None
        self.verify = bool(verify)
        _drop_exit_callbacks_in_forks()

    def __len__(self) -> int:
        return len(self.entries)

    _STATE = ("out", "url", "entries", "verify", "cache_bytes", "cache_dir", "prefetch")

    def __getstate__(self):  # no zarr handles, caches or threads cross a process boundary
        return {k: getattr(self, k) for k in self._STATE}

    def __setstate__(self, st):
        self.url, self.cache_bytes, self.cache_dir, self.prefetch = None, 2 * 2**30, None, 2
        for k, v in st.items():
            setattr(self, k, v)
        self.verify = st.get("verify", True)
        self._groups, self._meta, self._images, self._pid, self._cache = {}, {}, {}, None, None

    def where(self, shard_path: str) -> str:
        """The shard as a user names it (a path or a URL)."""
        return f"{self.url}/{shard_path}" if self.url else str(self.out / shard_path)

    @property
    def manifest_name(self) -> str:
        return f"{self.out}/manifest.parquet"

    def cache(self):
        """This process's :class:`ShardCache` (URL readers only), made on first use."""
        if self._cache is None:
            from freescale_core.store.shards_remote import default_cache_dir, shared_cache

            info = _torch_data().get_worker_info()
            w, W = (0, 1) if info is None else (info.id, info.num_workers)
            import hashlib

            tag = hashlib.sha256(self.url.encode()).hexdigest()[:12]
            root = (self.cache_dir or default_cache_dir()) / f"{tag}-w{w}of{W}"
            shards = {e["shard_path"]: (e["shard_sha256"], int(e["shard_bytes"]))
                      for e in self.entries}
            self._cache = shared_cache(self.url, shards, self.cache_bytes // W, root,
                                       self.prefetch)
        return self._cache

    def plan(self, entry_ids) -> None:
        """The entries this process will read, in order: a URL reader prefetches their
        shards ahead (a local reader ignores it)."""
        if self.url:
            self._fresh()
            self.cache().plan([self.entries[i]["shard_path"] for i in entry_ids])

    def _fresh(self) -> None:
        if self._pid != os.getpid():  # a forked worker: never reuse the parent's handles
            self._groups, self._meta, self._images, self._pid = {}, {}, {}, os.getpid()
            self._cache = None
            _fresh_worker()

    def group(self, shard_path: str):
        import zarr

        self._fresh()
        if self.url:  # every read goes through the cache: it pins the shard being read
            p = self.cache().get(shard_path)
        g = self._groups.get(shard_path)
        if g is None:
            if not self.url:
                p = self.out / shard_path
                if not p.is_dir():
                    raise StoreError(f"shard {p} named by {self.manifest_name} is missing")
                if self.verify:
                    sha = next(e["shard_sha256"] for e in self.entries
                               if e["shard_path"] == shard_path)
                    check_shard(p, sha, self.out / "manifest.parquet")
            try:
                g = self._groups[shard_path] = zarr.open_group(str(p), mode="r")
            except Exception as e:  # noqa: BLE001 - a damaged zarr.json
                raise StoreError(f"shard {self.where(shard_path)} cannot be opened: "
                                 f"{type(e).__name__}: {e}") from e
        return g

    SMALL = ("fxfycxcy", "world_from_cam", "is_free", "view_id", "frame_index", "edges/src",
             "edges/dst", "edges/wiou")

    def meta(self, shard_path: str) -> dict[str, np.ndarray]:
        """The small per-view arrays of a shard (everything but images), read once per
        process: a zarr read costs milliseconds whatever its size."""
        g = self.group(shard_path)
        m = self._meta.get(shard_path)
        if m is None:
            with _naming(self.where(shard_path)):
                m = self._meta[shard_path] = {k: np.asarray(g[k][:]) for k in self.SMALL}
        return m

    def scene_views(self, i: int) -> SceneViews:
        """The :class:`SceneViews` of manifest entry ``i``."""
        e = self.entries[i]
        g = self.meta(e["shard_path"])
        a, n = e["view_start"], e["n_views"]
        b, m = e["edge_start"], e["n_edges"]
        return SceneViews(
            scene_id=e["scene_id"], is_free=g["is_free"][a:a + n].astype(bool),
            frame_index=g["frame_index"][a:a + n].astype(np.int64),
            edges=(g["edges/src"][b:b + m].astype(np.int64) - a,
                   g["edges/dst"][b:b + m].astype(np.int64) - a,
                   g["edges/wiou"][b:b + m].astype(np.float32)))

    def load(self, i: int, rows, confidence: bool = False) -> dict[str, np.ndarray]:
        """Arrays of views ``rows`` (scene rows, any order, repeats allowed) of entry ``i``;
        with ``confidence``, also ``"confidence"`` ``[n, R, R]`` uint8 (x 255, the fixer's
        per-pixel confidence; 255 for photos), None when the shard has none."""
        e = self.entries[i]
        g = self.group(e["shard_path"])
        rows = np.asarray(rows, np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= e["n_views"]):
            raise IndexError(f"scene {e['scene_id']}: view rows {rows.tolist()} outside "
                             f"0..{e['n_views'] - 1}")
        idx = rows + e["view_start"]
        uniq, inv = np.unique(idx, return_inverse=True)
        meta = self.meta(e["shard_path"])
        out = {k: meta[k][idx] for k in ("fxfycxcy", "world_from_cam", "is_free", "view_id",
                                         "frame_index")}
        with _naming(self.where(e["shard_path"])):
            img = self._images.get(e["shard_path"])
            if img is None:  # opening an array reads its metadata: once per shard and process
                img = self._images[e["shard_path"]] = g["images"]
            # one chunk per view: per-view reads beat an orthogonal selection here
            out["images"] = np.stack([np.asarray(img[int(k)]) for k in uniq])[inv]
            if confidence:
                out["confidence"] = None
                if "confidence" in g:
                    c = g["confidence"]
                    out["confidence"] = np.stack([np.asarray(c[int(k)]) for k in uniq])[inv]
        return out


@contextlib.contextmanager
def _naming(shard: str | Path):
    """A chunk that cannot be read or decoded (truncated: zstd's ``RuntimeError``) fails in
    one line naming the shard."""
    try:
        yield
    except (StoreError, IndexError):
        raise
    except Exception as e:  # noqa: BLE001 - zarr / codec errors name no file
        raise StoreError(f"shard {shard} cannot be read ({type(e).__name__}: {e}); it is "
                         f"damaged: `freescale shards verify` and re-pack") from e


def scene_views_from_shard(reader: ShardReader, i: int) -> SceneViews:
    """The sampler's input record for manifest entry ``i`` of a :class:`ShardReader`."""
    return reader.scene_views(i)


def _to_sample(arrs: dict, vs, scene_id: str) -> dict:
    import torch

    n_in = len(vs.input_ids)
    return {
        # numpy, single-threaded: torch's intra-op pool only thrashes on a tensor this small
        "images": torch.from_numpy(np.ascontiguousarray(
            arrs["images"].transpose(0, 3, 1, 2), np.float32) * np.float32(1 / 255)),
        "fxfycxcy": torch.from_numpy(arrs["fxfycxcy"].astype(np.float32)),
        "world_from_cam": torch.from_numpy(arrs["world_from_cam"].astype(np.float32)),
        "is_free": torch.from_numpy(arrs["is_free"].astype(bool)),
        "view_id": torch.from_numpy(arrs["view_id"].astype(np.int64)),
        "frame_index": torch.from_numpy(arrs["frame_index"].astype(np.int64)),
        "target_weight": torch.as_tensor(np.asarray(vs.target_weight, np.float32)),
        "n_input": n_in,
        "scene_id": scene_id,
    }


def _draw(reader: ShardReader, sampler, i: int, rng: np.random.Generator, n_views: int | None):
    sv = reader.scene_views(i)
    vs = sampler.sample(sv, rng)
    rows = np.concatenate([np.asarray(vs.input_ids, np.int64),
                           np.asarray(vs.target_ids, np.int64)])
    if n_views is not None and len(rows) != n_views:
        raise StoreError(f"sampler {type(sampler).__name__} returned {len(rows)} views for "
                         f"scene {sv.scene_id}, expected a fixed {n_views}")
    return _to_sample(reader.load(i, rows), vs, sv.scene_id)


def _torch_data():
    from torch.utils import data

    return data


class ShardDataset(_torch_data().Dataset):
    """Map-style: item ``i`` is a sample of scene entry ``i // samples_per_scene``.

    Args:
        out: shard folder.
        sampler: a view sampler (default :class:`RandomViewSampler` 4 inputs + 2 targets).
        seed: base seed; ``set_epoch(e)`` changes the draws per epoch.
        samples_per_scene: items per scene per epoch.
        scenes: restrict to these scene ids.
        verify: check each shard's SHA-256 against the manifest before its first read in a
            process (a damaged shard fails naming it instead of giving wrong images).
        cache_bytes, cache_dir, prefetch: shards at a URL (:class:`ShardReader`); the
            map-style dataset fetches a shard when an item needs it (no prefetch order).
    """

    def __init__(self, out, sampler=None, seed: int = 0, samples_per_scene: int = 1,
                 scenes: list[str] | None = None, verify: bool = True,
                 cache_bytes: int = 2 * 2**30, cache_dir=None, prefetch: int = 2):
        self.reader = ShardReader(out, scenes, verify=verify, cache_bytes=cache_bytes,
                                  cache_dir=cache_dir, prefetch=prefetch)
        self.sampler = sampler or RandomViewSampler()
        self.seed, self.epoch = int(seed), 0
        self.samples_per_scene = int(samples_per_scene)
        self.n_views = _fixed_views(self.sampler)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.reader) * self.samples_per_scene

    def __getitem__(self, i: int) -> dict:
        if not 0 <= i < len(self):
            raise IndexError(i)
        rng = np.random.default_rng([self.seed, self.epoch, int(i)])
        return _draw(self.reader, self.sampler, int(i) // self.samples_per_scene, rng,
                     self.n_views)


class ShardIterableDataset(_torch_data().IterableDataset):
    """Streams samples scene by scene, shard by shard (sequential reads within a shard).

    Each epoch the shards are visited in a seeded random order and the scene entries are
    split across DataLoader workers (worker ``w`` takes entries ``w, w + W, ...`` of that
    order), each drawing ``samples_per_scene`` samples with
    ``default_rng([seed, epoch, entry, k])``.

    Shards at a URL are read through each worker's bounded cache (``cache_bytes`` in all,
    split among the workers), with the next ``prefetch`` shards of the worker's order
    fetched in the background; the samples are the same as from a local copy.
    """

    def __init__(self, out, sampler=None, seed: int = 0, samples_per_scene: int = 1,
                 scenes: list[str] | None = None, shuffle: bool = True, verify: bool = True,
                 cache_bytes: int = 2 * 2**30, cache_dir=None, prefetch: int = 2):
        self.reader = ShardReader(out, scenes, verify=verify, cache_bytes=cache_bytes,
                                  cache_dir=cache_dir, prefetch=prefetch)
        self.sampler = sampler or RandomViewSampler()
        self.seed, self.epoch = int(seed), 0
        self.samples_per_scene = int(samples_per_scene)
        self.shuffle = shuffle
        self.n_views = _fixed_views(self.sampler)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.reader) * self.samples_per_scene

    def entry_order(self) -> list[int]:
        ents = self.reader.entries
        shards = sorted({e["shard"] for e in ents})
        if self.shuffle:
            rng = np.random.default_rng([self.seed, self.epoch])
            shards = [shards[k] for k in rng.permutation(len(shards))]
        rank = {s: k for k, s in enumerate(shards)}
        return sorted(range(len(ents)), key=lambda i: (rank[ents[i]["shard"]], i))

    def __iter__(self):
        info = _torch_data().get_worker_info()
        w, W = (0, 1) if info is None else (info.id, info.num_workers)
        mine = self.entry_order()[w::W]
        self.reader.plan(mine)
        for i in mine:
            for k in range(self.samples_per_scene):
                rng = np.random.default_rng([self.seed, self.epoch, i, k])
                yield _draw(self.reader, self.sampler, i, rng, self.n_views)


def _fixed_views(sampler) -> int | None:
    src = sampler if hasattr(sampler, "n_input") else getattr(sampler, "config", None)
    n_in, n_t = getattr(src, "n_input", None), getattr(src, "n_target", None)
    return None if n_in is None or n_t is None else int(n_in) + int(n_t)


def worker_init_fn(worker_id: int = 0) -> None:
    """``DataLoader(..., worker_init_fn=worker_init_fn)``: a forked worker drops the state it
    inherited from the parent process (see :func:`_fresh_worker`). :class:`ShardDataset` and
    :class:`ShardIterableDataset` do this themselves; pass it for any other dataset read in
    forked workers of a process that ran Prefect (a flow, a task, a test harness)."""
    _fresh_worker()


_AT_FORK = []


def _drop_exit_callbacks_in_forks() -> None:
    """Once per process: every child forked from now on drops the parent's thread-exit
    callbacks at the fork itself (see :func:`_fresh_worker`), so a DataLoader worker that is
    handed no sample (more workers than batches) exits cleanly too; dropping them on the first
    read alone left such a worker with the parent's callbacks, and its exit code 1 failed the
    epoch. The threads those callbacks stop exist only in the parent."""
    if not _AT_FORK:
        _AT_FORK.append(True)
        os.register_at_fork(after_in_child=_clear_thread_exit_callbacks)


def _clear_thread_exit_callbacks() -> None:
    import threading

    callbacks = getattr(threading, "_threading_atexits", None)
    if isinstance(callbacks, list):
        callbacks.clear()


def _fresh_worker() -> None:
    """In a DataLoader worker, leave the parent's process state behind:

    * SIGTERM ends the process quietly again. A forked worker inherits the parent's SIGTERM
      handler (Prefect's, or the CLI's that turns it into an exception). When a worker is slow
      to leave, the DataLoader's shutdown sends it SIGTERM; the inherited handler then raised
      inside the worker, which exited with code 1 and failed the whole iteration ("DataLoader
      worker exited unexpectedly") on a loaded machine.
    * The parent's thread-exit callbacks are dropped. Prefect's background services (log and
      event workers) register one with ``threading._register_atexit``; a forked worker inherits
      the list and runs them when it exits, where the services' state is gone, so the callback
      raised (``AssertionError`` in ``QueueService._drain``) and the worker exited with code 1
      after its last batch: "DataLoader worker exited unexpectedly" at the end of an epoch.
      The threads they stop exist only in the parent.
    """
    import signal

    if _torch_data().get_worker_info() is not None:
        try:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
        except ValueError:  # not the worker's main thread
            pass
        _clear_thread_exit_callbacks()

