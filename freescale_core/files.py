"""Atomic files: a file is written beside its final name and renamed into place, so a reader
never sees half of it (used by the store and by every flow that writes results)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import time
import uuid
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from freescale_core.errors import StoreError

__all__ = ["atomic_path", "clean_stale_temps", "temp_name", "write_bytes_atomic",
           "write_json_atomic"]

HOST = socket.gethostname().replace("-", "_")[:32] or "host"
STALE_TEMP_SECONDS = 6 * 3600


def temp_name(path: str | Path) -> Path:
    """The temporary name a file or folder is written under before it is renamed to ``path``:
    ``.NAME.tmp-HOST-PID-RANDOM``, so that :func:`clean_stale_temps` can tell one whose writer
    died from one being written."""
    path = Path(path)
    return path.with_name(f".{path.name}.tmp-{HOST}-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def writer_gone(p: Path, owner: list[str], max_age: float) -> bool:
    """Whether the writer of ``p`` is gone: ``owner`` = [host, pid, ...] from its name; a pid of
    this host that no longer exists (not this process), or, when the owner cannot be checked
    (another host, an older name), ``max_age`` seconds untouched."""
    if len(owner) >= 3 and owner[0] == HOST and owner[1].isdigit():
        return int(owner[1]) != os.getpid() and not _pid_alive(int(owner[1]))
    try:
        return time.time() - p.lstat().st_mtime > max_age
    except OSError:
        return False


def clean_stale_temps(folder: str | Path, max_age: float = STALE_TEMP_SECONDS,
                      recursive: bool = True) -> list[str]:
    """Delete the temporary files and folders (:func:`temp_name`) under ``folder`` whose writer
    is known dead (this host, a pid that no longer exists) or, when the writer cannot be
    checked (another host, an older name), untouched for ``max_age`` seconds. Called by a
    scene's new writer (it holds the scene's lock, so nothing live of its own is removed).
    ``recursive=False``: ``folder`` itself only. Returns the paths removed, relative to
    ``folder``."""
    folder = Path(folder)
    removed = []
    for p in sorted((folder.rglob if recursive else folder.glob)(".*.tmp-*")):
        if any(q.name.startswith(".staging-") for q in p.relative_to(folder).parents):
            continue  # a publish's staging folder has its own rule (store.clean_stale_staging)
        if writer_gone(p, p.name.rsplit(".tmp-", 1)[1].split("-"), max_age):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(str(p.relative_to(folder)))
    return removed


# --------------------------------------------------------------------------- atomic files
@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically.

    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_name(path)
    try:
        yield tmp
        if tmp.is_dir():
            raise StoreError(f"atomic_path is for files, got a folder: {tmp}")
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_json_atomic(path: str | Path, obj: Any) -> None:
    write_bytes_atomic(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default).encode())


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
