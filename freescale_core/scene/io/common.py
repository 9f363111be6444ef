"""Helpers shared by the scene readers: image listing, natural order, checks, atomic caches."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import uuid
from pathlib import Path
from typing import Callable

import numpy as np

from freescale_core.errors import (
    CorruptImageError,
    ImageCountMismatchError,
    MissingInputError,
    SceneError,
)
from freescale_core.scene.images import natural_key, read_rgb

IMAGE_EXTS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"})
CACHE_VERSION = 1  # bump when the cached layout or the undistortion changes


class MissingImageError(ImageCountMismatchError, MissingInputError):
    """An image the camera model lists is not on disk (a count mismatch *and* a missing file)."""


class CorruptModelError(SceneError):
    """A camera model file (COLMAP, transforms.json, PLY) exists but cannot be parsed."""


def list_images(folder: Path, recursive: bool = True) -> list[str]:
    """Image files under ``folder`` as posix paths relative to it, naturally sorted.

    Hidden files and folders (``.freescale_cache``, ``.DS_Store``) are skipped. Symbolic
    links are followed, to files and (when ``recursive``) to folders, wherever they point, as
    the input fingerprint follows them; a link back to a folder above it (a loop) is not
    followed.
    """
    folder = Path(folder)
    out = []
    chains = {str(folder): {os.path.realpath(folder)}}  # a folder -> its ancestors' real paths
    for d, dirs, files in os.walk(folder, followlinks=True):
        chain = chains.pop(d)
        keep = []
        for x in sorted(dirs) if recursive else []:
            sub = os.path.join(d, x)
            real = os.path.realpath(sub)
            if x.startswith(".") or real in chain:  # hidden, or a link back up (a loop)
                continue
            chains[sub] = chain | {real}
            keep.append(x)
        dirs[:] = keep
        for f in files:
            p = Path(d) / f
            if f.startswith(".") or p.suffix.lower() not in IMAGE_EXTS or not p.is_file():
                continue
            out.append(p.relative_to(folder).as_posix())
    return sorted(out, key=natural_key)


def check_image_set(scene_id: str, images_dir: Path, model_names: list[str],
                    model_file: Path, folders: list[str] | None = None) -> list[str]:
    """Pre-filter: the model's images and the folder's images must be the same set.

    Args:
        images_dir: folder the model's names are relative to.
        model_names: every image name the model lists.
        model_file: the model file (named in the message).
        folders: sub-folders of ``images_dir`` (relative, non-recursive) to compare with; None
            compares with all images under ``images_dir`` (recursive).
    Returns:
        The image files on disk (relative names).
    Raises:
        MissingImageError: a model image is not on disk (message gives both counts).
        ImageCountMismatchError: the folder holds images the model does not know.
    """
    images_dir = Path(images_dir)
    if folders is None:
        on_disk = list_images(images_dir)
        where = f"{images_dir.name}/"
    else:
        on_disk = []
        for f in folders:
            sub = images_dir / f if f else images_dir
            if sub.is_dir():
                on_disk += [(Path(f) / n).as_posix() if f else n
                            for n in list_images(sub, recursive=False)]
        where = ", ".join(f"{f}/" if f else "./" for f in folders)
    disk_set, model_set = set(on_disk), set(model_names)
    missing = [n for n in model_names if n not in disk_set]
    extra = [n for n in on_disk if n not in model_set]
    counts = f"{len(model_names)} images in the camera model ({Path(model_file).name}), " \
             f"{len(on_disk)} image files in {where}"
    if missing:
        raise MissingImageError(
            scene_id, f"image count mismatch: {counts}; {len(missing)} model image(s) missing "
            f"on disk, first {missing[:5]}", images_dir / missing[0])
    if extra:
        raise ImageCountMismatchError(
            scene_id, f"image count mismatch: {counts}; {len(extra)} image file(s) not in the "
            f"model, first {extra[:5]}", images_dir / extra[0])
    return on_disk


def decode_sizes(scene_id: str, paths: list[Path], check: bool = True) -> np.ndarray:
    """``[N, 2]`` (width, height) of each image; decodes every image when ``check``.

    Raises:
        MissingInputError / CorruptImageError naming the scene and the file.
    """
    sizes = np.zeros((len(paths), 2), np.int64)
    for i, p in enumerate(paths):
        if check:
            img = read_rgb(p, scene_id)
            sizes[i] = img.shape[1], img.shape[0]
        else:
            sizes[i] = header_size(scene_id, p)
    return sizes


def header_size(scene_id: str, path: Path) -> tuple[int, int]:
    """(width, height) of an image from its header only (no full decode)."""
    from PIL import Image, UnidentifiedImageError

    if not Path(path).is_file():
        raise MissingInputError(scene_id, "image file is missing", path)
    try:
        with Image.open(path) as im:
            return int(im.width), int(im.height)
    except (UnidentifiedImageError, OSError) as e:
        raise CorruptImageError(scene_id, f"image header cannot be read ({e})", path) from e


def inside_scene(scene_id: str, root: Path, rel: str | Path, what: str, model_file: Path,
                 allow_outside: bool = False) -> Path:
    """``root / rel``, refused (:class:`UnsafePathError`) when it lies outside ``root``.

    The check is lexical (``..`` and absolute paths), so a scene may still keep its images
    behind a symbolic link inside its folder. ``allow_outside`` is the explicit opt-in
    (``ingest.allow_outside_paths``)."""
    from freescale_core.errors import UnsafePathError

    r = Path(os.path.normpath(os.path.abspath(root)))
    p = Path(os.path.normpath(os.path.join(r, str(rel))))
    if not allow_outside and p != r and r not in p.parents:
        raise UnsafePathError(
            scene_id, f"{what} {str(rel)!r} points outside the scene folder {r} (resolves to "
            f"{p}); a scene reads only inside its own folder (set "
            "ingest.allow_outside_paths=true to allow this)", model_file)
    return p


def fingerprint(obj: dict) -> str:
    """Short stable hash of a JSON-able dict (cache keys)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def file_stamp(path: Path, content: bool = False) -> list:
    """Identity of a file for cache keys: name, size, mtime (or a content hash)."""
    st = Path(path).stat()
    if content:
        return [Path(path).name, hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]]
    return [Path(path).name, st.st_size, st.st_mtime_ns]


def folder_is_writable(folder: Path) -> bool:
    """True when ``folder`` may be written: permitted *and* not marked read-only.

    ``os.access`` alone says yes to root for a folder whose mode is ``r-x``; a data set that
    was made read-only on purpose (like ``../shared/datasets``) must not receive a cache.
    """
    import stat

    try:
        st = Path(folder).stat()
    except OSError:
        return False
    marked = bool(st.st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    return marked and os.access(folder, os.W_OK)


def default_cache_root(scene_root: Path, scene_id: str, cache_dir: Path | None) -> Path:
    """Folder holding the scene's cached derivatives.

    ``cache_dir/<scene_id>`` when given; else ``<scene>/.freescale_cache`` when the scene
    folder is writable (see :func:`folder_is_writable`); else a per-user temp folder keyed
    by the scene's absolute path (recorded in ``Scene.extras["cache_dir"]``).
    """
    if cache_dir is not None:
        return Path(cache_dir) / scene_id
    root = Path(scene_root)
    if folder_is_writable(root):
        return root / ".freescale_cache"
    tag = hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:8]
    return Path(tempfile.gettempdir()) / f"freescale_cache_{os.getuid()}" / f"{scene_id}-{tag}"


MANIFEST = "_manifest.json"


def read_manifest(folder: Path, key: str) -> dict | None:
    """The manifest of a complete cache folder whose key matches, else None."""
    f = Path(folder) / MANIFEST
    if not f.is_file():
        return None
    try:
        m = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    if m.get("key") != key or m.get("version") != CACHE_VERSION:
        return None
    if not all((Path(folder) / rel).is_file() for rel in m.get("files", [])):
        return None
    return m


def build_cached_folder(target: Path, key: str,
                        build: Callable[[Path], dict]) -> tuple[dict, bool]:
    """Return the manifest of ``target``, building it atomically if absent or stale.

    ``build(tmp_dir)`` fills a fresh temporary sibling folder and returns the manifest body
    (must contain ``files``: paths relative to the folder). The folder is renamed into place
    only when complete, so a reader never sees half a cache; a stale folder is moved aside and
    deleted. Concurrent builders are safe: the loser discards its copy, and a folder another
    builder installed with the same key while this one ran is kept, never swapped under its
    readers.

    Returns:
        ``(manifest, reused)``.
    """
    target = Path(target)
    m = read_manifest(target, key)
    if m is not None:
        return m, True
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.parent / f".{target.name}.tmp-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        body = build(tmp)
        body = dict(body, key=key, version=CACHE_VERSION)
        (tmp / MANIFEST).write_text(json.dumps(body, indent=1))
        # another process may have installed the same build while this one ran: keep its
        # folder (a reader may already hold its paths) and discard this copy
        m = read_manifest(target, key)
        if m is not None:
            return m, True
        stale = None
        if target.exists():
            stale = target.parent / f".{target.name}.stale-{uuid.uuid4().hex[:8]}"
            try:
                os.replace(target, stale)
            except OSError:
                stale = None
        try:
            os.replace(tmp, target)
        except OSError:
            # another process won the race; use its folder if it is complete
            m = read_manifest(target, key)
            if m is None:
                raise
            return m, True
        finally:
            if stale is not None:  # deleted only once the new folder is in place
                shutil.rmtree(stale, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return body, False
