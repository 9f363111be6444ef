"""What every export shares: atomic output folders, image writing, the result record."""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from freescale_core.errors import StoreError
from freescale_core.store.layout import link_or_copy  # noqa: F401 (one definition; the writers import it from here)


@dataclass
class ExportResult:
    """What an export wrote.

    Attributes:
        format: ``nerfstudio``, ``lvsm``, ``gsplat`` or ``colmap``.
        out: the output folder (final location).
        scenes: scene ids exported.
        files: a few notable files, relative to ``out`` (for the summary).
        counts: per scene ``{"train": n, "free": m}``.
        load_command: the command that loads the export in the target tool.
    """

    format: str
    out: Path
    scenes: list[str]
    files: list[str] = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    load_command: str = ""

    def summary(self) -> str:
        lines = [f"{self.format} export of {len(self.scenes)} scene(s) written to {self.out}"]
        for s in self.scenes:
            c = self.counts.get(s, {})
            lines.append(f"  {s}: {c.get('train', 0)} captured + {c.get('free', 0)} free views")
        for f in self.files[:12]:
            lines.append(f"  {f}")
        if len(self.files) > 12:
            lines.append(f"  ... {len(self.files) - 12} more files")
        lines.append("load with:")
        lines.append(f"  {self.load_command}")
        return "\n".join(lines)


@contextlib.contextmanager
def atomic_dir(out: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """Build an output folder under a temporary name beside ``out``; rename it on success.

    A reader never sees a half-written export: on an exception the temporary folder is
    removed and ``out`` is untouched. With ``overwrite`` an existing ``out`` is moved aside,
    replaced, then deleted (two renames; a crash between them leaves ``out`` absent and the
    old export under ``.<name>.old-*``). A target that is, lies inside or (with
    ``overwrite``) holds a store or a shards folder is refused: an export never deletes data
    it does not own.
    """
    from freescale_core.store.store import data_around

    out = Path(out).absolute()
    # never inside a store or a shards folder, and --overwrite never deletes one
    why = data_around(out, below=overwrite and out.exists())
    if why is not None:
        raise StoreError(f"export target refused: {why}; choose another folder")
    if out.exists() and not overwrite:
        if out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        else:
            raise StoreError(f"export target {out} exists; pass --overwrite to replace it")
    if out.exists() and not out.is_dir():
        raise StoreError(f"export target {out} is a file, not a folder")
    tag = uuid.uuid4().hex[:8]
    tmp = out.parent / f".{out.name}.tmp-{tag}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp.mkdir()
    except OSError as e:  # under a file, a read-only mount, no permission
        raise StoreError(f"cannot write the export {out}: {e.strerror or e}") from e
    try:
        yield tmp
        old = None
        if out.exists():
            old = out.parent / f".{out.name}.old-{tag}"
            os.rename(out, old)
        os.rename(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def write_png(path: Path, rgb: np.ndarray) -> None:
    """Write ``[H, W, 3]`` uint8 RGB (or ``[H, W]`` uint8/uint16) as PNG."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 else rgb
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise StoreError(f"could not encode {path}")
    path.write_bytes(buf.tobytes())


def scene_sets(store_root: str | Path, scenes: list[str] | None):
    """The :class:`FreeViewSet` of each requested (default: every ``ok``) scene."""
    from freescale_core.store.reader import open_scenes

    sets = open_scenes(store_root, scenes)
    if not sets:
        raise StoreError(f"no published scene in {store_root}")
    return sets


def frame_order(fvs) -> np.ndarray:
    """Rows of ``fvs.dataset_views()`` with captured views in capture order first, then the
    free views in view-id order (the order every export writes frames in)."""
    v = fvs.dataset_views()
    train = np.flatnonzero(~v.is_free)
    train = train[np.argsort(v.capture_index[train], kind="stable")]
    return np.concatenate([train, np.flatnonzero(v.is_free)]).astype(np.int64)
