"""Fixer training pairs: one in-memory record and its on-disk layout.

A *pair* is what the fixer learns from: a render of a reconstruction at a camera whose photo
that reconstruction never saw, the K nearest training photos warped into that camera with
the rendered depth, and the held-out photo as the target.

On disk (written by :mod:`freescale_core.eval.fixer_pairs`, read here)::

    PAIRS/
      <scene_id>/<fold>/            one folder per scene and fold, made visible by one rename
        pairs.zarr/<pair_id>/       render [H,W,3] u8, alpha [H,W] u8, depth [H,W] f32,
                                    warps [K,H,W,3] u8, warp_weight [K,H,W] u8 (x255),
                                    warp_angle [K,H,W] f16 (deg), target [H,W,3] u8,
                                    mask [H,W] u8 (255 = pixel is scored / trained on)
        pairs.parquet               one row per pair (columns: PAIR_COLUMNS)
        done.json                   the key the folder was made with (config, code, inputs)

``mask`` is all 255 unless the capture has object masks. ``warp_weight`` is the warp's
validity (the reproject rectifier's evidence classes, in bounds) times its triangulation-angle
kernel, so 0 where the warped photo says nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

__all__ = ["FixerSample", "PAIR_COLUMNS", "model_input", "n_input_channels",
           "write_pair_group", "write_pair_folder", "read_pair_folder", "load_pairs",
           "pair_folders"]

# columns of pairs.parquet
PAIR_COLUMNS = ("pair_id", "scene_id", "fold", "budget", "view_index", "view_name",
                "height", "width", "k", "source", "psnr_render", "psnr_warp0",
                "warp_coverage", "alpha_mean")


@dataclass
class FixerSample:
    """One training pair (float arrays in [0, 1] unless said otherwise).

    Attributes:
        render: ``[H, W, 3]`` the reconstruction's render at the held-out camera.
        alpha: ``[H, W]`` its accumulated opacity.
        depth: ``[H, W]`` rendered camera-z depth (world units).
        warps: ``[K, H, W, 3]`` the K nearest training photos warped into the view.
        warp_weight: ``[K, H, W]`` validity x angle kernel of each warp (0 = no evidence).
        warp_angle: ``[K, H, W]`` triangulation angle of each warp in degrees.
        target: ``[H, W, 3]`` the held-out photo (or the oracle image at a free-view pose).
        mask: ``[H, W]`` bool, pixels that are scored / trained on.
        meta: the pair's row (``PAIR_COLUMNS``).
    """

    render: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray
    warps: np.ndarray
    warp_weight: np.ndarray
    warp_angle: np.ndarray
    target: np.ndarray
    mask: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def hw(self) -> tuple[int, int]:
        return int(self.render.shape[0]), int(self.render.shape[1])

    @property
    def k(self) -> int:
        return int(self.warps.shape[0])


def n_input_channels(k: int) -> int:
    """Channels of :func:`model_input`: render (3) + alpha (1) + per warp RGB (3) + weight (1)."""
    return 4 + 4 * int(k)


def model_input(render: np.ndarray, alpha: np.ndarray, warps: np.ndarray,
                warp_weight: np.ndarray, k: int) -> np.ndarray:
    """The fixer's input ``[4 + 4k, H, W]`` float32: render, alpha, then per warp its RGB and
    weight. Fewer than ``k`` warps are padded with zeros (weight 0: no evidence); more are cut
    (the first ``k`` are the nearest)."""
    H, W = render.shape[:2]
    ch = [np.moveaxis(np.asarray(render, np.float32), -1, 0),
          np.asarray(alpha, np.float32)[None]]
    warps = np.asarray(warps, np.float32).reshape(-1, H, W, 3)
    warp_weight = np.asarray(warp_weight, np.float32).reshape(-1, H, W)
    for i in range(int(k)):
        if i < len(warps):
            ch += [np.moveaxis(warps[i], -1, 0), warp_weight[i][None]]
        else:
            ch += [np.zeros((3, H, W), np.float32), np.zeros((1, H, W), np.float32)]
    return np.ascontiguousarray(np.concatenate(ch, axis=0), dtype=np.float32)


def _u8(a: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(a, np.float64) * 255.0), 0, 255).astype(np.uint8)


def write_pair_group(group, s: FixerSample) -> None:
    """Write one pair into an open zarr group (``group`` is the pair's own sub-group)."""
    def put(name, arr):
        group.create_array(name, data=np.ascontiguousarray(arr), overwrite=True)

    put("render", _u8(s.render))
    put("alpha", _u8(s.alpha))
    put("depth", np.asarray(s.depth, np.float32))
    put("warps", _u8(s.warps))
    put("warp_weight", _u8(s.warp_weight))
    put("warp_angle", np.asarray(s.warp_angle, np.float16))
    put("target", _u8(s.target))
    put("mask", np.where(np.asarray(s.mask, bool), 255, 0).astype(np.uint8))


def _read_group(group, meta: dict) -> FixerSample:
    f = lambda n: np.asarray(group[n][...])  # noqa: E731
    return FixerSample(render=f("render").astype(np.float32) / 255.0,
                       alpha=f("alpha").astype(np.float32) / 255.0,
                       depth=f("depth").astype(np.float32),
                       warps=f("warps").astype(np.float32) / 255.0,
                       warp_weight=f("warp_weight").astype(np.float32) / 255.0,
                       warp_angle=f("warp_angle").astype(np.float32),
                       target=f("target").astype(np.float32) / 255.0,
                       mask=f("mask") > 127, meta=dict(meta))


def read_pair_folder(folder: str | Path) -> Iterator[FixerSample]:
    """Every pair of one ``<scene_id>/<fold>`` folder, in ``pairs.parquet`` order."""
    import pyarrow.parquet as pq
    import zarr

    folder = Path(folder)
    rows = pq.read_table(folder / "pairs.parquet").to_pylist()
    root = zarr.open_group(str(folder / "pairs.zarr"), mode="r")
    for row in rows:
        yield _read_group(root[row["pair_id"]], row)


def pair_folders(root: str | Path, scenes: Sequence[str] | None = None,
                 exclude: Sequence[str] = ()) -> list[Path]:
    """Complete pair folders under ``root`` (those with ``done.json``), sorted; only
    ``scenes`` when given, never those in ``exclude``."""
    root = Path(root)
    out = []
    for done in sorted(root.glob("*/*/done.json")):
        scene = done.parent.parent.name
        if scene.startswith(".") or done.parent.name.startswith("."):
            continue
        if scenes is not None and scene not in scenes:
            continue
        if scene in exclude:
            continue
        out.append(done.parent)
    return out


def load_pairs(root: str | Path, scenes: Sequence[str] | None = None,
               exclude: Sequence[str] = ()) -> list[FixerSample]:
    """All pairs under ``root`` (see :func:`pair_folders` for the scene filters)."""
    return [s for folder in pair_folders(root, scenes, exclude)
            for s in read_pair_folder(folder)]


def write_pair_folder(folder: str | Path, samples: Sequence[FixerSample], key: dict) -> Path:
    """Write ``samples`` as one ``<scene_id>/<fold>`` folder, atomically: built in a hidden
    sibling, then renamed into place (an older folder of the same name is replaced)."""
    import json
    import shutil
    import uuid

    import pyarrow as pa
    import pyarrow.parquet as pq
    import zarr

    folder = Path(folder)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.with_name(f".{folder.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        tmp.mkdir()
        root = zarr.open_group(str(tmp / "pairs.zarr"), mode="w")
        rows = []
        for s in samples:
            pid = str(s.meta["pair_id"])
            write_pair_group(root.create_group(pid), s)
            rows.append({c: s.meta.get(c) for c in PAIR_COLUMNS})
        pq.write_table(pa.Table.from_pylist(rows) if rows else pa.table(
            {c: pa.array([], pa.string()) for c in PAIR_COLUMNS}), tmp / "pairs.parquet")
        (tmp / "done.json").write_text(json.dumps(key, indent=2, sort_keys=True, default=str))
        old = None
        if folder.exists():
            old = folder.with_name(f".{folder.name}.old-{uuid.uuid4().hex[:8]}")
            folder.rename(old)
        tmp.rename(folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return folder
