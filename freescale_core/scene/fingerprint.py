"""Content fingerprint of a scene folder: what the ingest checkpoint and the "already
complete" check are keyed on, so an edited input is never silently ignored.

Every file under the scene folder counts (images, masks, the COLMAP model, transforms.json,
a user PLY ...) except hidden entries (``.freescale_cache`` and the like, which the engine
itself may write). A file's identity is its relative path, size and mtime; small files other than images (the camera
model, transforms.json: at most ``hash_below`` bytes) are hashed by content as well, so a
model rewritten with the same size and mtime still counts as changed. Images are not read
(a thousand photos would cost seconds on every run).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

__all__ = ["input_fingerprint"]

IMAGE_EXTS = {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp", ".exr"}


def input_fingerprint(path: str | Path, hash_below: int = 1 << 20) -> str:
    """16-hex-digit fingerprint of the inputs under ``path`` (a folder, or a transforms.json
    whose folder is used)."""
    root = Path(path)
    if root.is_file():
        root = root.parent
    h = hashlib.sha256()
    entries = []
    for d, dirs, files in os.walk(root, followlinks=True):
        dirs[:] = sorted(x for x in dirs if not x.startswith("."))
        for f in files:
            if f.startswith("."):
                continue
            p = Path(d) / f
            try:
                st = p.stat()
            except OSError:  # a dangling link: its absence is part of the identity
                entries.append((p.relative_to(root).as_posix(), -1, 0, ""))
                continue
            digest = ""
            if st.st_size <= hash_below and p.suffix.lower() not in IMAGE_EXTS:
                try:
                    digest = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
                except OSError:
                    digest = "unreadable"
            entries.append((p.relative_to(root).as_posix(), st.st_size, st.st_mtime_ns, digest))
    for e in sorted(entries):
        h.update(repr(e).encode())
    return h.hexdigest()[:16]
