"""COLMAP sparse models (binary or text) via pycolmap, with precise errors.

pycolmap's own errors do not say which camera or image is wrong ("Camera model does not
exist", a failed stream check on a NaN); the text and binary scans below find the offending
line first so the error names the scene, the file, the camera or image, and the value.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from freescale_core.errors import CameraModelError, DegenerateSceneError, MissingInputError
from freescale_core.scene.io.assemble import RawModel
from freescale_core.scene.io.common import CorruptModelError
from freescale_core.scene.io.undistort import known_model_names

MODEL_FILES = ("cameras", "images", "points3D")


def model_ext(folder: Path) -> str | None:
    """``.bin`` or ``.txt`` when ``folder`` holds a complete COLMAP model, else None."""
    folder = Path(folder)
    for ext in (".bin", ".txt"):
        if all((folder / f"{m}{ext}").is_file() for m in MODEL_FILES):
            return ext
    return None


def has_model_files(folder: Path) -> bool:
    """True when ``folder`` holds at least a cameras and an images file."""
    folder = Path(folder)
    return any((folder / f"cameras{e}").is_file() or (folder / f"images{e}").is_file()
               for e in (".bin", ".txt"))


def find_model_dir(root: Path) -> Path | None:
    """The model folder of a scene: ``sparse/0``, ``sparse``, or ``root`` itself."""
    root = Path(root)
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if has_model_files(cand):
            return cand
    sparse = root / "sparse"
    if sparse.is_dir():
        subs = sorted((p for p in sparse.iterdir() if p.is_dir() and has_model_files(p)),
                      key=lambda p: p.name)
        if subs:
            return subs[0]
    return None


# --------------------------------------------------------------------------- diagnostics
def _data_lines(path: Path):
    """(line_number, stripped line) of non-empty, non-comment lines."""
    with open(path, encoding="utf-8", errors="replace") as f:
        for i, line in enumerate(f, 1):
            s = line.strip()
            if s and not s.startswith("#"):
                yield i, s


def scan_cameras_txt(scene_id: str, path: Path) -> None:
    """Raise a precise :class:`CameraModelError` for an unknown model or bad parameters."""
    import pycolmap

    known = set(known_model_names())
    for lineno, s in _data_lines(path):
        parts = s.split()
        if len(parts) < 4:
            raise CorruptModelError(scene_id, f"line {lineno}: expected 'CAMERA_ID MODEL WIDTH "
                                    f"HEIGHT PARAMS...', found {s[:80]!r}", path)
        cam_id, model = parts[0], parts[1]
        if model not in known:
            raise CameraModelError(
                scene_id, f"camera {cam_id} (line {lineno}) has unknown camera model {model!r}; "
                f"known models: {', '.join(sorted(known))}", path)
        try:
            vals = [float(v) for v in parts[2:]]
        except ValueError:
            raise CameraModelError(scene_id, f"camera {cam_id} (line {lineno}): non-numeric "
                                   f"size or parameters {parts[2:]}", path) from None
        n_params = len(pycolmap.Camera.create_from_model_name(0, model, 1.0, 1, 1).params)
        if len(vals) - 2 != n_params:
            raise CameraModelError(
                scene_id, f"camera {cam_id} (line {lineno}): model {model} takes {n_params} "
                f"parameters, found {len(vals) - 2}", path)
        if not np.all(np.isfinite(vals)):
            raise CameraModelError(scene_id, f"camera {cam_id} (line {lineno}): non-finite "
                                   f"parameters {parts[2:]}", path)


def scan_images_txt(scene_id: str, path: Path) -> None:
    """Raise :class:`DegenerateSceneError` naming the image whose pose is NaN / unparsable."""
    with open(path, encoding="utf-8", errors="replace") as f:
        lines = f.readlines()
    i = 0
    while i < len(lines):
        s = lines[i].strip()
        i += 1
        if not s or s.startswith("#"):
            continue
        parts = s.split()
        name = " ".join(parts[9:]) if len(parts) >= 10 else "?"
        try:
            vals = [float(v) for v in parts[1:8]]
            if len(parts) < 10:
                raise ValueError
        except ValueError:
            raise CorruptModelError(
                scene_id, f"line {i}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', "
                f"found {s[:80]!r}", path) from None
        if not np.all(np.isfinite(vals)):
            raise DegenerateSceneError(
                scene_id, f"image '{name}' (id {parts[0]}, line {i}) has a non-finite pose "
                f"{parts[1:8]}", path)
        if np.linalg.norm(vals[:4]) < 1e-12:
            raise DegenerateSceneError(
                scene_id, f"image '{name}' (id {parts[0]}, line {i}) has a zero quaternion",
                path)
        i += 1  # the POINTS2D line that always follows (it may be empty)


def scan_cameras_bin(scene_id: str, path: Path) -> None:
    """Raise :class:`CameraModelError` for an unknown model id in ``cameras.bin``."""
    import pycolmap

    ids = {int(v): k for k, v in pycolmap.CameraModelId.__members__.items() if k != "INVALID"}
    data = Path(path).read_bytes()
    try:
        (n,) = struct.unpack_from("<Q", data, 0)
        off = 8
        for _ in range(n):
            cam_id, model_id, w, h = struct.unpack_from("<iiQQ", data, off)
            off += 24
            if model_id not in ids:
                raise CameraModelError(
                    scene_id, f"camera {cam_id} has unknown camera model id {model_id}; known "
                    f"ids: {sorted(ids)}", path)
            k = len(pycolmap.Camera.create_from_model_name(0, ids[model_id], 1.0, 1, 1).params)
            params = struct.unpack_from(f"<{k}d", data, off)
            off += 8 * k
            if not np.all(np.isfinite(params)):
                raise CameraModelError(scene_id, f"camera {cam_id} ({ids[model_id]}) has "
                                       f"non-finite parameters {list(params)}", path)
    except struct.error:
        raise CorruptModelError(scene_id, "cameras.bin is truncated", path) from None


# --------------------------------------------------------------------------- reading
def read_reconstruction(scene_id: str, model_dir: Path):
    """``pycolmap.Reconstruction`` of ``model_dir``, after the diagnostic scans."""
    import pycolmap

    model_dir = Path(model_dir)
    ext = model_ext(model_dir)
    if ext is None:
        missing = [f"{m}.bin|.txt" for m in MODEL_FILES
                   if not any((model_dir / f"{m}{e}").is_file() for e in (".bin", ".txt"))]
        what = ", ".join(missing) or "a consistent set of .bin or .txt files"
        raise MissingInputError(scene_id, f"incomplete COLMAP model: missing {what}", model_dir)
    if ext == ".txt":
        scan_cameras_txt(scene_id, model_dir / "cameras.txt")
        scan_images_txt(scene_id, model_dir / "images.txt")
    else:
        scan_cameras_bin(scene_id, model_dir / "cameras.bin")
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except (IndexError, KeyError) as e:  # pycolmap: a track or image naming an absent id
        msg = str(e).strip().strip("'\"").splitlines()[0][:300] or type(e).__name__
        raise CorruptModelError(scene_id, f"COLMAP model cannot be read: {msg} (a point track "
                                "in points3D or an image in images names an id the model does "
                                "not list)", model_dir / f"points3D{ext}") from e
    except (ValueError, RuntimeError, OSError) as e:
        msg = str(e).strip().splitlines()[0][:300] if str(e).strip() else type(e).__name__
        raise CorruptModelError(scene_id, f"COLMAP model cannot be read: {msg}",
                                model_dir) from e


def raw_from_reconstruction(scene_id: str, rec, model_dir: Path, images_dir: Path,
                            check_counts: bool = True) -> RawModel:
    """The registered images, their cameras and the points of a pycolmap reconstruction."""
    ext = model_ext(model_dir) or ".bin"
    reg = set(rec.reg_image_ids())
    all_names, names, poses, cams = [], [], [], []
    for image_id in sorted(rec.images):
        img = rec.images[image_id]
        all_names.append(img.name)
        if image_id not in reg:
            continue
        names.append(img.name)
        T = np.eye(4)
        T[:3, :4] = img.cam_from_world().matrix()
        poses.append(T)
        cams.append(rec.cameras[img.camera_id])
    pts = rec.points3D
    n_pts = len(pts)
    xyz = np.empty((n_pts, 3), np.float64)
    rgb = np.empty((n_pts, 3), np.uint8)
    pos = {image_id: k for k, image_id in enumerate(i for i in sorted(rec.images) if i in reg)}
    lens = np.zeros(n_pts, np.int64)
    views: list[int] = []
    for k, p in enumerate(pts.values()):
        xyz[k] = p.xyz
        rgb[k] = p.color
        track = [pos.get(e.image_id, -1) for e in p.track.elements]
        lens[k] = len(track)
        views += track
    views_arr = np.asarray(views, np.int64)
    finite = np.isfinite(xyz).all(axis=1)
    extras = {"model_dir": str(model_dir), "n_model_images": len(all_names),
              "n_registered": len(names)}
    if not finite.all():
        extras["n_dropped_nonfinite_points"] = int((~finite).sum())
        xyz, rgb = xyz[finite], rgb[finite]
        views_arr = views_arr[np.repeat(finite, lens)]
        lens = lens[finite]
    ptr = np.concatenate([[0], np.cumsum(lens)]).astype(np.int64)
    return RawModel(
        names=names,
        cam_from_world=np.stack(poses) if poses else np.zeros((0, 4, 4)),
        cameras=cams, points_xyz=xyz, points_rgb=rgb, images_dir=Path(images_dir),
        pose_file=Path(model_dir) / f"images{ext}", camera_file=Path(model_dir) / f"cameras{ext}",
        source_format="colmap", model_names=all_names if check_counts else None,
        stamp_files=[Path(model_dir) / f"{m}{ext}" for m in ("cameras", "images")],
        extras=extras, points_tracks=(ptr, views_arr),
    )


def read_colmap_raw(scene_id: str, model_dir: Path, images_dir: Path) -> RawModel:
    """Read and pre-check a COLMAP model; images are named relative to ``images_dir``."""
    rec = read_reconstruction(scene_id, model_dir)
    raw = raw_from_reconstruction(scene_id, rec, model_dir, images_dir)
    if len(raw.points_xyz) == 0:
        raise DegenerateSceneError(scene_id, "the COLMAP model has no 3D points",
                                   Path(model_dir) / f"points3D{model_ext(model_dir)}")
    return raw
