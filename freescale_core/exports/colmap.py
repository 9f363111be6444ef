"""Export to a COLMAP text model: ``OUT/<scene>/images/`` + ``sparse/0/{cameras,images,points3D}.txt``.

For tools that read only COLMAP. Every dataset view (captured + free) is an image with its own
``PINHOLE`` camera (``fx fy cx cy`` in pixels, COLMAP's convention, which is ours); poses are
``cam_from_world`` (quaternion wxyz + t) in the store's world. Image names are
``<k:05d>_<name>`` (captured views, in capture order) and ``<k:05d>_free_<view_id>.png``, so
the natural name order of the files is the export's frame order. ``points3D.txt`` holds the
sparse points with empty tracks (the store keeps no 2D observations).
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath


from freescale_core.exports.common import (ExportResult, atomic_dir, frame_order, link_or_copy,
                                           scene_sets, write_png)
from freescale_core.geometry.cameras import cam_from_world_to_colmap, invert_pose


def image_name(k: int, fvs_name: str, view_id: int, is_free: bool) -> str:
    if is_free:
        return f"{k:05d}_free_{view_id:05d}.png"
    return f"{k:05d}_{PurePosixPath(fvs_name).name}"


def write_model_text(model_dir: Path, cams, rows, names: list[str], xyz, rgb) -> None:
    """``cameras.txt``, ``images.txt``, ``points3D.txt`` in ``model_dir``: image ``k`` is view
    ``rows[k]`` of ``cams`` (its own PINHOLE camera, pose cam_from_world) named ``names[k]``;
    the points ``xyz`` / ``rgb`` with empty tracks."""
    cam_lines = ["# Camera list with one line of data per camera:",
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
                 f"# Number of cameras: {len(rows)}"]
    img_lines = ["# Image list with two lines of data per image:",
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)",
                 f"# Number of images: {len(rows)}"]
    for k, (r, name) in enumerate(zip(rows, names)):
        cid = k + 1
        cam_lines.append(f"{cid} PINHOLE {int(cams.width[r])} {int(cams.height[r])} "
                         f"{float(cams.fx[r])!r} {float(cams.fy[r])!r} {float(cams.cx[r])!r} {float(cams.cy[r])!r}")
        q, t = cam_from_world_to_colmap(invert_pose(cams.world_from_cam[r]))
        img_lines.append(f"{cid} {' '.join(repr(float(x)) for x in q)} "
                         f"{' '.join(repr(float(x)) for x in t)} {cid} {name}")
        img_lines.append("")
    pts = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           f"# Number of points: {len(xyz)}"]
    pts += [f"{i + 1} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0"
            for i, (p, c) in enumerate(zip(xyz.tolist(), rgb.tolist()))]
    model_dir.mkdir(parents=True)
    (model_dir / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (model_dir / "images.txt").write_text("\n".join(img_lines) + "\n")
    (model_dir / "points3D.txt").write_text("\n".join(pts) + "\n")


def export_scene(fvs, out: Path) -> dict:
    v = fvs.dataset_views()
    order = frame_order(fvs)
    names = []
    n_free = 0
    for k, r in enumerate(order):
        vid = int(v.view_id[r])
        name = image_name(k, str(v.name[r]), vid, bool(v.is_free[r]))
        if v.is_free[r]:
            write_png(out / "images" / name, fvs.rgb(vid))
            n_free += 1
        else:
            link_or_copy(fvs.image_path(vid), out / "images" / name)
        names.append(name)
    xyz, rgb = fvs.points()
    write_model_text(out / "sparse" / "0", v.cameras, list(order), names, xyz, rgb)
    return {"train": int(len(order) - n_free), "free": n_free}


def export(store_root, out, scenes: list[str] | None = None,
           overwrite: bool = False) -> ExportResult:
    sets = scene_sets(store_root, scenes)
    final = Path(out).absolute()
    res = ExportResult("colmap", final, [s.scene_id for s in sets])
    with atomic_dir(final, overwrite) as tmp:
        for fvs in sets:
            d = tmp / fvs.scene_id
            d.mkdir()
            res.counts[fvs.scene_id] = export_scene(fvs, d)
            res.files.append(f"{fvs.scene_id}/sparse/0/images.txt")
    first = final / sets[0].scene_id
    res.load_command = (f"python -c \"import pycolmap; print(pycolmap.Reconstruction("
                        f"'{first}/sparse/0').summary())\"  # or: colmap gui --import_path "
                        f"{first}/sparse/0 --image_path {first}/images")
    return res
