"""Content fingerprint of a scene folder: what the ingest checkpoint and the "already
complete" check are keyed on, so an edited input is never silently ignored.

Every file under the scene folder counts (images, masks, the COLMAP model, transforms.json,
a user PLY ...) except hidden entries (``.freescale_cache`` and the like, which the engine
itself may write). A file's identity is its relative path and a hash of its content
(BLAKE2b, about 1 GB/s), so an image edited with the same size and mtime still counts as
changed. A file's digest is reused while its (size, mtime, ctime, inode) stay the same: from
this process, or from ``$XDG_CACHE_HOME/freescale/fingerprint/`` (``~/.cache``) across runs.
ctime cannot be set back by a user, so restoring a file's mtime after an edit does not hide
the edit.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from freescale_core.files import temp_name

__all__ = ["file_digest", "input_fingerprint"]

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr"}
_MEMO: dict[str, tuple[tuple, str]] = {}


def file_digest(p: Path) -> str:
    """BLAKE2b (16 hex digits) of the file's bytes."""
    h = hashlib.blake2b(digest_size=8)
    with open(p, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def _cache_file(root: Path) -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    tag = hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:16]
    return base / "freescale" / "fingerprint" / f"{tag}.json"


def _load_cache(root: Path) -> dict:
    try:
        return json.loads(_cache_file(root).read_text())
    except (OSError, ValueError):
        return {}


def _save_cache(root: Path, cache: dict) -> None:
    p = _cache_file(root)
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmp = temp_name(p)
        tmp.write_text(json.dumps(cache))
        os.replace(tmp, p)
    except OSError:  # a read-only home: the digests are recomputed next time
        pass


def input_fingerprint(path: str | Path, hash_below: int | None = None) -> str:
    """16-hex-digit fingerprint of the inputs under ``path`` (a folder, or a transforms.json
    whose folder is used): every file's relative path and content hash.

    Args:
        path: the scene folder.
        hash_below: unused (every file is hashed by content); kept for old callers.
    """
    root = Path(path)
    if root.is_file():
        root = root.parent
    disk = _load_cache(root)
    new_cache: dict = {}
    entries = []
    for d, dirs, files in os.walk(root, followlinks=True):
        dirs[:] = sorted(x for x in dirs if not x.startswith("."))
        for f in files:
            if f.startswith("."):
                continue
            p = Path(d) / f
            rel = p.relative_to(root).as_posix()
            try:
                st = p.stat()
            except OSError:  # a dangling link: its absence is part of the identity
                entries.append((rel, -1, ""))
                continue
            ident = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino]
            memo = _MEMO.get(str(p))
            if memo is not None and list(memo[0]) == ident:
                digest = memo[1]
            elif rel in disk and disk[rel][:4] == ident:
                digest = disk[rel][4]
            else:
                try:
                    digest = file_digest(p)
                except OSError:
                    digest = "unreadable"
            _MEMO[str(p)] = (tuple(ident), digest)
            new_cache[rel] = [*ident, digest]
            entries.append((rel, st.st_size, digest))
    if new_cache != disk:
        _save_cache(root, new_cache)
    h = hashlib.sha256()
    for e in sorted(entries):
        h.update(repr(e).encode())
    return h.hexdigest()[:16]
