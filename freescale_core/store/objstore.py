"""Helpers of the store on object storage (the class is
:class:`freescale_core.store.store.ObjectStore`) (``s3://``, ``gs://``, any fsspec URL): same layout, same API
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

LEASE_SECONDS = float(os.environ.get("FREESCALE_LEASE_SECONDS", 120))
_VERSION_RE = "v[0-9][0-9][0-9][0-9]"


class CommitConflictError(StoreError):
    """Another writer made a version of the scene visible first (the conditional ``CURRENT``
    write failed); the version this writer uploaded stays invisible."""


def is_url(s: Any) -> bool:
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


