"""Training shards: many scenes of a store packed into fixed-capacity zarr shards at one
resolution, with a parquet manifest (``freescale shards pack STORE OUT``).

Layout (documented in ``docs/DATASET.md``)::

    OUT/
      manifest.parquet          one row per (shard, scene): the only thing readers trust
      shards/000000.zarr/       zarr v3 group, whole scenes, at most ``views_per_shard`` views
        images          [V, R, R, 3] uint8   one chunk per view
        fxfycxcy        [V, 4]  float32      pixels of the R x R image
        world_from_cam  [V, 4, 4] float64    OpenCV axes, camera-to-world
        is_free         [V] bool
        frame_index     [V] int64            capture order (captured views), -1 (free views)
        view_id         [V] int64            views.parquet id in the source version
        mode            [V] int8             index into attrs["modes"] (0 = train)
        score_f, brisque [V] float32         view-graph node score, BRISQUE/100 (NaN: unset)
        orig_size       [V, 2] int32         (height, width) before resize / crop
        edges/src, edges/dst [E] int64       shard rows (view-graph edges, src < dst)
        edges/wiou      [E] float32
        attrs: format, resolution, resize, modes, scenes [{scene_id, view_start, n_views,
               edge_start, n_edges}]
      .lock                     held while packing

Images: the shorter side is resized to R (``cv2.INTER_AREA`` when shrinking, bicubic when
enlarging; the longer side to ``round(long * R / short)``), then centre-cropped to R x R
(crop offset ``(new - R) // 2``); intrinsics follow exactly: ``fx, cx *= new_w / w``,
``fy, cy *= new_h / h``, then ``cx -= x0``, ``cy -= y0`` (pixel centres at +0.5, so scaling
is exact).

Atomicity and increments: every shard is written under ``shards/.tmp-*`` and renamed; the
manifest is replaced atomically after each new shard. A killed pack leaves the previous
manifest (plus any shard it already committed), and shard folders pack wrote that no
manifest row names are ignored by readers and deleted by the next pack; any other folder
under ``shards/`` is never touched. Manifest rows are keyed by (source store, scene). Packing again adds only scenes that are
not in the manifest at their current store version; a scene whose store version changed is
packed again and its old row dropped.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import hashlib
import os
import re
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from freescale_core import __version__
from freescale_core.errors import StoreError
from freescale_core.store.shards_remote import _dir_bytes_and_sha, files_bytes_and_sha  # noqa: F401
from freescale_core.store.store import Store, write_parquet_atomic

SHARD_FORMAT = "freescale-shard/1"
MODES = ("train", "orbit", "spiral", "lemniscate", "interpolation", "move_up", "move_down",
         "move_left", "move_right", "dolly_in", "dolly_out")
MANIFEST_COLUMNS = {
    "shard": pa.string(), "shard_path": pa.string(), "scene_id": pa.string(),
    "scene_index": pa.int64(), "view_start": pa.int64(), "n_views": pa.int64(),
    "n_train": pa.int64(), "n_free": pa.int64(), "edge_start": pa.int64(),
    "n_edges": pa.int64(), "resolution": pa.int64(), "shard_views": pa.int64(),
    "shard_bytes": pa.int64(), "source_store": pa.string(), "source_version": pa.string(),
    "config_hash": pa.string(), "engine_version": pa.string(), "scene_sha256": pa.string(),
    "shard_sha256": pa.string(), "packed_at": pa.string(),
}


# --------------------------------------------------------------------------- images
def resize_crop(img: np.ndarray, fxfycxcy: np.ndarray, R: int) -> tuple[np.ndarray, np.ndarray]:
    """Resize the shorter side to ``R``, centre-crop to ``R x R``; intrinsics to match.

    Args:
        img: ``[h, w, 3]`` uint8.
        fxfycxcy: ``[4]`` pixels of ``img``.
    Returns:
        ``([R, R, 3] uint8, [4] float64 pixels of the output)``.
    """
    import cv2

    h, w = img.shape[:2]
    s = R / min(h, w)
    if w <= h:
        nw, nh = R, max(R, int(round(h * s)))
    else:
        nw, nh = max(R, int(round(w * s))), R
    interp = cv2.INTER_AREA if s < 1 else cv2.INTER_CUBIC
    out = cv2.resize(img, (nw, nh), interpolation=interp) if (nw, nh) != (w, h) else img
    x0, y0 = (nw - R) // 2, (nh - R) // 2
    out = np.ascontiguousarray(out[y0:y0 + R, x0:x0 + R])
    fx, fy, cx, cy = np.asarray(fxfycxcy, np.float64)
    sx, sy = nw / w, nh / h
    return out, np.array([fx * sx, fy * sy, cx * sx - x0, cy * sy - y0])


# --------------------------------------------------------------------------- one scene
@dataclass
class PackedScene:
    """One scene's arrays, ready to be appended to a shard (rows in dataset-view order)."""

    scene_id: str
    images: np.ndarray          # [V, R, R, 3] uint8
    fxfycxcy: np.ndarray        # [V, 4] float32
    world_from_cam: np.ndarray  # [V, 4, 4] float64
    is_free: np.ndarray         # [V] bool
    frame_index: np.ndarray     # [V] int64
    view_id: np.ndarray         # [V] int64
    mode: np.ndarray            # [V] int8
    score_f: np.ndarray         # [V] float32
    brisque: np.ndarray         # [V] float32
    orig_size: np.ndarray       # [V, 2] int32
    edges: tuple                # (src [E], dst [E]) scene rows, wiou [E]
    meta: dict = field(default_factory=dict)
    confidence: np.ndarray | None = None  # [V, R, R] uint8, 255 = photo / no map

    def __len__(self) -> int:
        return len(self.view_id)

    def sha256(self) -> str:
        h = hashlib.sha256()
        for a in (self.images, self.fxfycxcy, self.world_from_cam, self.is_free,
                  self.frame_index, self.view_id, self.mode, *self.edges,
                  *(() if self.confidence is None else (self.confidence,))):
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()


def pack_scene(fvs, R: int) -> PackedScene:
    """Read a :class:`~freescale_core.store.reader.FreeViewSet` into a :class:`PackedScene`."""
    v = fvs.dataset_views()
    n = len(v)
    images = np.zeros((n, R, R, 3), np.uint8)
    intr = np.zeros((n, 4), np.float64)
    c = v.cameras
    conf = np.full((n, R, R), 255, np.uint8)
    for r in range(n):
        img = fvs.rgb(int(v.view_id[r]))
        k = np.array([c.fx[r], c.fy[r], c.cx[r], c.cy[r]])
        images[r], intr[r] = resize_crop(img, k, R)
        cm = fvs.confidence(int(v.view_id[r])) if v.is_free[r] else None
        if cm is not None:  # the fixer's confidence, resized and cropped with its image
            c8 = np.clip(np.rint(cm * 255.0), 0, 255).astype(np.uint8)
            conf[r] = resize_crop(np.repeat(c8[..., None], 3, -1), k, R)[0][..., 0]
    pos = {int(x): k for k, x in enumerate(v.view_id)}
    src, dst, w = fvs.graph()
    mode = np.array([MODES.index(m) if m in MODES else -1 for m in v.mode], np.int8)
    return PackedScene(
        scene_id=fvs.scene_id, images=images, fxfycxcy=intr.astype(np.float32),
        world_from_cam=c.world_from_cam.copy(), is_free=v.is_free.astype(bool),
        frame_index=np.where(v.is_free, -1, v.capture_index).astype(np.int64),
        view_id=v.view_id.astype(np.int64), mode=mode,
        score_f=v.score_f.astype(np.float32), brisque=v.brisque.astype(np.float32),
        orig_size=np.stack([c.height, c.width], 1).astype(np.int32), confidence=conf,
        edges=(np.array([pos[int(s)] for s in src], np.int64),
               np.array([pos[int(d)] for d in dst], np.int64), np.asarray(w, np.float32)))


# --------------------------------------------------------------------------- one shard
def write_shard(path: Path, scenes: list[PackedScene], R: int) -> list[dict]:
    """Write ``scenes`` as one zarr shard at ``path`` (a fresh folder). Returns per-scene
    placement records ``{scene_id, view_start, n_views, edge_start, n_edges}``."""
    import zarr

    cat = lambda name: np.concatenate([getattr(s, name) for s in scenes])  # noqa: E731
    V = sum(len(s) for s in scenes)
    recs, src, dst, wiou = [], [], [], []
    v0 = e0 = 0
    for s in scenes:
        ne = len(s.edges[0])
        recs.append({"scene_id": s.scene_id, "view_start": v0, "n_views": len(s),
                     "edge_start": e0, "n_edges": ne})
        src.append(s.edges[0] + v0)
        dst.append(s.edges[1] + v0)
        wiou.append(s.edges[2])
        v0 += len(s)
        e0 += ne
    root = zarr.open_group(str(path), mode="w")
    img = root.create_array("images", shape=(V, R, R, 3), dtype="uint8", chunks=(1, R, R, 3))
    img[:] = cat("images")
    if all(s.confidence is not None for s in scenes):
        cf = root.create_array("confidence", shape=(V, R, R), dtype="uint8", chunks=(1, R, R))
        cf[:] = cat("confidence")
    for name in ("fxfycxcy", "world_from_cam", "is_free", "frame_index", "view_id", "mode",
                 "score_f", "brisque", "orig_size"):
        root.create_array(name, data=cat(name))
    eg = root.create_group("edges")
    eg.create_array("src", data=np.concatenate(src).astype(np.int64))
    eg.create_array("dst", data=np.concatenate(dst).astype(np.int64))
    eg.create_array("wiou", data=np.concatenate(wiou).astype(np.float32))
    root.attrs.update({"format": SHARD_FORMAT, "resolution": R, "modes": list(MODES),
                       "resize": "shorter side to R (INTER_AREA shrink / INTER_CUBIC enlarge), "
                                 "centre crop R x R", "scenes": recs})
    return recs


# --------------------------------------------------------------------------- manifest
def read_manifest(out: str | Path) -> pa.Table:
    """The shard manifest of ``out``, a folder or a URL (FileNotFoundError when there is
    none)."""
    from freescale_core.store.objstore import is_url, local_of

    if is_url(out):
        from freescale_core.store.shards_remote import read_url_manifest

        return read_url_manifest(str(out))
    p = Path(local_of(out)) / "manifest.parquet"
    if not p.is_file():
        raise FileNotFoundError(f"no shard manifest at {p} (run `freescale shards pack`)")
    return pq.read_table(p)


def shards_location(out: str | Path) -> str:
    """Where a shard set lives, as a run records it: the URL, or the folder's absolute path."""
    from freescale_core.store.objstore import is_url, local_of

    return str(out).rstrip("/") if is_url(out) else str(Path(local_of(out)).absolute())


def manifest_sha256(out: str | Path) -> str:
    """SHA-256 of the shard manifest's bytes (a folder or a URL): what a resumed training run
    checks it still reads."""
    from freescale_core.store.objstore import is_url, local_of

    if is_url(out):
        import fsspec

        fs, base = fsspec.core.url_to_fs(str(out).rstrip("/"))
        data = fs.cat_file(f"{base}/manifest.parquet")
    else:
        data = (Path(local_of(out)) / "manifest.parquet").read_bytes()
    return hashlib.sha256(data).hexdigest()


def _empty_manifest() -> pa.Table:
    return pa.table({k: pa.array([], t) for k, t in MANIFEST_COLUMNS.items()})


def _rows_table(rows: list[dict]) -> pa.Table:
    return pa.table({k: pa.array([r[k] for r in rows], t) for k, t in MANIFEST_COLUMNS.items()})


@contextlib.contextmanager
def _lock(out: Path):
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".lock", "a+") as f:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f.fileno(), fcntl.LOCK_UN)


def _shard_numbers(d: Path) -> list[int]:
    return sorted(int(p.name.split(".")[0]) for p in d.glob("[0-9]*.zarr")
                  if p.name.split(".")[0].isdigit())


@dataclass
class PackResult:
    out: Path
    new_shards: list[str]
    packed: list[str]
    skipped: list[str]
    manifest: pa.Table

    def summary(self) -> str:
        m = self.manifest
        lines = [f"{self.out}: packed {len(self.packed)} scene(s) into {len(self.new_shards)} "
                 f"new shard(s); {len(self.skipped)} already packed at their store version",
                 f"manifest: {m.num_rows} (shard, scene) rows, "
                 f"{len(set(m.column('shard').to_pylist()))} shards, "
                 f"{sum(m.column('n_views').to_pylist())} views"]
        if self.packed:
            lines.append("  new: " + ", ".join(self.packed))
        lines.append(f"browse: freescale shards ls {self.out}")
        return "\n".join(lines)


def pack(store_root: str | Path, out: str | Path, scenes: list[str] | None = None,
         resolution: int = 256, views_per_shard: int = 1024, _after_shard=None) -> PackResult:
    """Pack scenes of a store into training shards under ``out`` (see the module doc).

    Args:
        store_root: the FreeScale store (a folder or a URL: ``s3://bucket/store``).
        out: shard folder (created; an existing one is extended), or a URL
            (``s3://bucket/shards``: each shard is built locally and uploaded as one zip
            object of its own, then the manifest is PUT last; see ``shards_remote``).
        scenes: scene ids (default: every ``ok`` scene of the store).
        resolution: R, the square image side.
        views_per_shard: shard capacity; whole scenes only, so a scene with more views than
            this gets a shard of its own.
        _after_shard: test hook called with the shard name after each committed shard.
    Raises:
        StoreError: unknown scene, or ``out`` holds shards at another resolution.
    """
    if resolution < 8:
        raise ValueError(f"resolution must be >= 8, got {resolution}")
    if views_per_shard < 1:
        raise ValueError(f"views_per_shard must be >= 1, got {views_per_shard}")
    from freescale_core.store.objstore import is_url, local_of
    from freescale_core.store.store import data_around, is_store

    if is_url(store_root):
        store = Store(store_root)
        store_abs = str(store)
        try:
            all_ids = store.scene_ids()
        except OSError as e:
            raise StoreError(f"store {store_root} cannot be listed: {e}") from None
        if not all_ids:
            raise StoreError(f"{store_root} is not a FreeScale store (no scene status under "
                             f"{store_abs}/scenes/; run `freescale run --store "
                             f"{store_root}` first)")
    else:
        store_root = local_of(store_root)
        src = Path(store_root)
        if not src.exists():
            raise StoreError(f"store {store_root} does not exist")
        if not src.is_dir():
            raise StoreError(f"store {store_root} is a file, not a FreeScale store")
        if not is_store(src):
            raise StoreError(f"{store_root} is not a FreeScale store (no scenes/ folder with "
                             f"a manifest or scene status; run `freescale run` first)")
        store = Store(store_root)
        store_abs = str(src.absolute())
        all_ids = store.scene_ids()
    if is_url(out):
        from freescale_core.store.shards_remote import UrlShardsOut

        target = UrlShardsOut(str(out))
    else:
        out = Path(local_of(out)).absolute()
        why = data_around(out, below=False)
        if why is not None and not _is_shards_out(out):
            raise StoreError(f"shards output refused: {why}; pack into another folder")
        if out.exists() and not out.is_dir():
            raise StoreError(f"shards output {out} is a file, not a folder")
        if (out / "manifest.parquet").is_file() and not (out / "shards").is_dir():
            raise StoreError(f"{out} holds a manifest.parquet that is not a shard manifest; "
                             f"pack into another folder")
        target = LocalShardsOut(out)
    if scenes:
        scenes = list(dict.fromkeys(scenes))  # --scenes a a packs a once
        missing = [s for s in scenes if s not in all_ids]
        if missing:
            raise StoreError(f"scenes {missing} are not in the store {store_root}")
        ids = list(scenes)
    else:
        ids = [s for s in all_ids if store.read_status(s).get("status") == "ok"]
        if not ids:
            raise StoreError(f"store {store_root} has no ok scene to pack")
    try:
        return _pack(store, store_root, store_abs, target, ids, resolution, views_per_shard,
                     _after_shard)
    except OSError as e:  # a full disk, a read-only folder: the manifest stays the last one
        raise StoreError(f"packing into {target} failed: {e.strerror or e} "
                         f"({getattr(e, 'filename', '') or target}); the manifest is "
                         f"unchanged since the last committed shard") from e


def _is_shards_out(out: Path) -> bool:
    """``out`` is itself a shards folder (extended by packing again), not inside a store."""
    from freescale_core.store.store import data_around, is_shards

    if not is_shards(out):
        return False
    return data_around(out.parent, below=False) is None


class LocalShardsOut:
    """Where ``pack`` commits in a local folder: shards renamed into ``shards/``, the
    manifest replaced atomically, one packer at a time by ``flock`` on ``OUT/.lock``."""

    def __init__(self, out: Path):
        self.out = out
        self.sdir = out / "shards"

    def __str__(self) -> str:
        return str(self.out)

    def lock(self):
        return _lock(self.out)

    def prepare(self) -> None:
        self.sdir.mkdir(exist_ok=True)

    def manifest(self) -> pa.Table | None:
        return read_manifest(self.out) if (self.out / "manifest.parquet").is_file() else None

    def staging(self) -> Path:
        return self.sdir / f".tmp-{uuid.uuid4().hex[:8]}"

    def commit_shard(self, tmp: Path) -> tuple[str, str]:
        """Make the staged shard ``tmp`` a numbered one; ``(name, shard_path)``."""
        name = f"{max(_shard_numbers(self.sdir), default=-1) + 1:06d}"
        os.rename(tmp, self.sdir / f"{name}.zarr")
        return name, f"shards/{name}.zarr"

    def write_manifest(self, table: pa.Table) -> None:
        write_parquet_atomic(self.out / "manifest.parquet", table)

    def gc(self, rows: list[dict]) -> None:
        _gc(self.out, rows)


def _pack(store, store_root, store_abs: str, target, ids: list[str], resolution: int,
          views_per_shard: int, _after_shard) -> PackResult:
    from freescale_core.store.reader import FreeViewSet

    with target.lock():
        target.prepare()
        manifest = target.manifest()
        manifest = _empty_manifest() if manifest is None else manifest
        if set(MANIFEST_COLUMNS) - set(manifest.column_names):
            raise StoreError(f"{target}/manifest.parquet is not a shard manifest (columns "
                             f"{sorted(set(MANIFEST_COLUMNS) - set(manifest.column_names))[:3]}"
                             f" missing); pack into another folder")
        rows = manifest.to_pylist()
        res_in = {r["resolution"] for r in rows}
        if res_in and res_in != {resolution}:
            raise StoreError(f"{target} holds shards at resolution {sorted(res_in)}, not "
                             f"{resolution}; pack into another folder")
        target.gc(rows)  # shards of a killed pack
        have = {(r["scene_id"], r["source_store"], r["source_version"]) for r in rows}
        todo, skipped = [], []
        for sid in ids:
            st = store.read_status(sid)
            if st.get("status") != "ok":
                raise StoreError(f"scene {sid!r} is not ok in {store_root} "
                                 f"(status {st.get('status')!r})")
            fvs = FreeViewSet.open(store_root, sid)
            if (sid, store_abs, fvs.version) in have:
                skipped.append(sid)
            else:
                todo.append((fvs, st))
        new_shards, packed = [], []
        batch: list[tuple] = []
        last = [manifest]

        def flush():
            nonlocal rows
            if not batch:
                return
            tmp = target.staging()
            try:
                recs = write_shard(tmp, [p for p, _, _ in batch], resolution)
                nbytes, sha = _dir_bytes_and_sha(tmp)
                name, shard_path = target.commit_shard(tmp)
            finally:
                if tmp.exists():
                    shutil.rmtree(tmp, ignore_errors=True)
            now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
            V = sum(len(p) for p, _, _ in batch)
            # superseded versions: a row is (source store, scene), so the same scene id
            # packed from another store keeps its own row
            new_ids = {(store_abs, p.scene_id) for p, _, _ in batch}
            rows = [r for r in rows if (r["source_store"], r["scene_id"]) not in new_ids]
            for k, ((p, fvs, st), rec) in enumerate(zip(batch, recs)):
                rows.append({
                    "shard": name, "shard_path": shard_path, "scene_id": p.scene_id,
                    "scene_index": k, "view_start": rec["view_start"], "n_views": rec["n_views"],
                    "n_train": int((~p.is_free).sum()), "n_free": int(p.is_free.sum()),
                    "edge_start": rec["edge_start"], "n_edges": rec["n_edges"],
                    "resolution": resolution, "shard_views": V, "shard_bytes": nbytes,
                    "source_store": store_abs, "source_version": fvs.version,
                    "config_hash": str(st.get("config_hash", "")),
                    "engine_version": __version__, "scene_sha256": p.sha256(),
                    "shard_sha256": sha, "packed_at": now})
            last[0] = _rows_table(rows)
            target.write_manifest(last[0])
            new_shards.append(name)
            packed.extend(p.scene_id for p, _, _ in batch)
            batch.clear()
            target.gc(rows)
            if _after_shard is not None:
                _after_shard(name)

        for fvs, st in todo:
            p = pack_scene(fvs, resolution)
            if batch and sum(len(q) for q, _, _ in batch) + len(p) > views_per_shard:
                flush()
            batch.append((p, fvs, st))
        flush()
        return PackResult(target.out, new_shards, packed, skipped, last[0])


_TMP = re.compile(r"\.tmp-[0-9a-f]{8}")
_SHARD = re.compile(r"[0-9]{6}\.zarr")


def _written_by_pack(p: Path) -> bool:
    """A folder ``pack`` wrote: its temporary name, or a numbered shard whose zarr
    attributes carry the shard format. Nothing else under ``shards/`` is ever touched."""
    import json

    if _TMP.fullmatch(p.name):
        return True
    if not _SHARD.fullmatch(p.name):
        return False
    try:
        attrs = json.loads((p / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError):
        return False
    return attrs.get("format") == SHARD_FORMAT


def _gc(out: Path, rows: list[dict]) -> None:
    """Delete shard folders pack wrote that no manifest row names (a killed pack's,
    superseded ones); a user's folder under ``shards/`` stays."""
    live = {r["shard_path"] for r in rows}
    for p in (out / "shards").iterdir():
        rel = f"shards/{p.name}"
        if p.is_dir() and rel not in live and _written_by_pack(p):
            shutil.rmtree(p, ignore_errors=True)


def shard_sha256(p: Path) -> str:
    """The SHA-256 the manifest records for the shard folder ``p`` (every file's path and
    content)."""
    return _dir_bytes_and_sha(Path(p))[1]


def verify(out: str | Path) -> list[str]:
    """Recompute every shard's checksum; returns the shards that do not match the manifest
    (a missing shard folder does not match). ``out`` may be a URL (every shard is
    downloaded into memory, one at a time, and hashed)."""
    from freescale_core.store.objstore import is_url, local_of

    if is_url(out):
        from freescale_core.store.shards_remote import verify_url

        return verify_url(str(out))
    out = local_of(out)
    bad = []
    for r in {r["shard"]: r for r in read_manifest(out).to_pylist()}.values():
        p = Path(out) / r["shard_path"]
        if not p.is_dir() or shard_sha256(p) != r["shard_sha256"]:
            bad.append(r["shard"])
    return bad
