"""Export to nerfstudio: ``OUT/<scene>/transforms.json`` + ``images/`` (+ ``depths/``).

One folder per scene, loadable by nerfstudio's ``nerfstudio-data`` dataparser:

* ``transforms.json``: ``camera_model`` ``PINHOLE``; per frame ``fl_x fl_y cx cy w h`` (pixels
  of that frame's image, COLMAP pixel convention, which nerfstudio uses), ``transform_matrix``
  camera-to-world in OpenGL axes, in the store's world (no ``applied_transform``);
  ``train_filenames`` / ``val_filenames`` / ``test_filenames``; ``ply_file_path`` of the
  sparse points (``sparse_pc.ply``, splatfacto's initialisation); every frame carries a
  ``freescale`` record (``view_id``, ``is_free``, ``mode``, ``brisque``).
* Captured views: the published training images (hard links), in capture order, first.
  Free views: ``images/free_<view_id>.png``.
* ``--free-views train`` (default): free views are extra training views; val = test = every
  8th captured view. ``--free-views val``: training = captured views, val = test = free views.
* ``--depth``: ``depths/<image stem>.png`` 16-bit for every frame, value = depth /
  ``depth_unit_scale_factor`` (camera z in world units); captured views have no depth and get
  an all-zero PNG (0 = unknown, nerfstudio's depth losses ignore it).
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath

import numpy as np

from freescale_core.exports.common import (ExportResult, atomic_dir, frame_order, link_or_copy,
                                           scene_sets, write_png)
from freescale_core.geometry.cameras import world_from_cam_to_nerfstudio


def depth_scale(max_depth: float) -> float:
    """``depth_unit_scale_factor``: 1e-3 (millimetres when the unit is a metre) unless the
    deepest free-view pixel would not fit in 16 bits, then the next power of ten that fits."""
    s = 1e-3
    while max_depth / s > 65535:
        s *= 10
    return s


def export_scene(fvs, out: Path, free_views: str = "train", depth: bool = False) -> dict:
    """Write one scene into ``out`` (an existing folder). Returns ``{"train", "free"}``."""
    from freescale_core.scene.ply import write_ply_points

    if free_views not in ("train", "val"):
        raise ValueError(f"free_views must be 'train' or 'val', got {free_views!r}")
    v = fvs.dataset_views()
    order = frame_order(fvs)
    cams = v.cameras
    frames, captured, free = [], [], []
    scale = 1e-3
    if depth and v.is_free.any():
        scale = depth_scale(max(float(fvs.depth(int(v.view_id[r])).max()) for r in order
                                if v.is_free[r]))
    for r in order:
        vid = int(v.view_id[r])
        if v.is_free[r]:
            rel = f"images/free_{vid:05d}.png"
            write_png(out / rel, fvs.rgb(vid))
            free.append(rel)
        else:
            rel = (PurePosixPath("images") / str(v.name[r])).as_posix()
            link_or_copy(fvs.image_path(vid), out / rel)
            captured.append(rel)
        tm = world_from_cam_to_nerfstudio(cams.world_from_cam[r])
        fr = {"file_path": rel, "transform_matrix": tm.tolist(),
              "fl_x": float(cams.fx[r]), "fl_y": float(cams.fy[r]), "cx": float(cams.cx[r]),
              "cy": float(cams.cy[r]), "w": int(cams.width[r]), "h": int(cams.height[r]),
              "freescale": {"view_id": vid, "is_free": bool(v.is_free[r]),
                            "mode": str(v.mode[r]),
                            "brisque": None if not np.isfinite(v.brisque[r])
                            else float(v.brisque[r])}}
        if depth:
            drel = f"depths/{PurePosixPath(rel).stem}_{vid:05d}.png"
            h, w = int(cams.height[r]), int(cams.width[r])
            d = fvs.depth(vid) if v.is_free[r] else np.zeros((h, w), np.float32)
            write_png(out / drel, np.clip(np.round(d / scale), 0, 65535).astype(np.uint16))
            fr["depth_file_path"] = drel
        frames.append(fr)
    meta: dict = {"camera_model": "PINHOLE", "frames": frames}
    if depth:
        meta["depth_unit_scale_factor"] = scale
    if free_views == "train":
        meta["train_filenames"] = captured + free
        meta["val_filenames"] = meta["test_filenames"] = captured[::8]
    else:
        meta["train_filenames"] = captured
        meta["val_filenames"] = meta["test_filenames"] = free or captured[::8]
    xyz, rgb = fvs.points()
    write_ply_points(out / "sparse_pc.ply", xyz, rgb)
    meta["ply_file_path"] = "sparse_pc.ply"
    meta["freescale"] = {"scene_id": fvs.scene_id, "store_version": str(fvs.version_dir),
                         "free_views": free_views}
    (out / "transforms.json").write_text(json.dumps(meta, indent=1))
    return {"train": len(captured), "free": len(free)}


def export(store_root, out, scenes: list[str] | None = None, free_views: str = "train",
           depth: bool = False, overwrite: bool = False) -> ExportResult:
    """Export scenes of a store to ``out/<scene_id>/`` (atomically, as one folder)."""
    sets = scene_sets(store_root, scenes)
    final = Path(out).absolute()
    res = ExportResult("nerfstudio", final, [s.scene_id for s in sets])
    with atomic_dir(final, overwrite) as tmp:
        for fvs in sets:
            d = tmp / fvs.scene_id
            d.mkdir()
            res.counts[fvs.scene_id] = export_scene(fvs, d, free_views, depth)
            res.files.append(f"{fvs.scene_id}/transforms.json")
    first = final / sets[0].scene_id
    res.load_command = (f"ns-train splatfacto --data {first} nerfstudio-data  "
                        f"# or: ns-train nerfacto --data {first}")
    return res
