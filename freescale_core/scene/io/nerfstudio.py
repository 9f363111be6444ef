"""nerfstudio / DL3DV ``transforms.json`` scenes: reader, and a writer for tests and export.

Format (nerfstudio ``ns-process-data``, also DL3DV-10K): intrinsics ``fl_x fl_y cx cy w h``
and distortion ``k1 k2 (k3 k4) p1 p2`` with ``camera_model`` ("OPENCV", "OPENCV_FISHEYE",
"PINHOLE", ...) at the top level or per frame (a frame's keys override the top level);
``frames[*].file_path`` relative to the json; ``frames[*].transform_matrix`` camera-to-world in
OpenGL camera axes; optional ``applied_transform`` (3x4) that ns-process-data applied to the
COLMAP world (poses *and* the ``ply_file_path`` points live in that applied world); optional
``ply_file_path`` of the sparse points; optional ``frames[*].mask_path`` (object masks,
every frame or none). Pixel coordinates follow COLMAP's convention.

Poses and points are mapped back to the original world (``applied_transform`` undone) so a
scene read from COLMAP and from its transforms.json export agree.
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath

import numpy as np

from freescale_core.geometry.cameras import (
    CV_FROM_GL,
    invert_pose,
    nerfstudio_to_world_from_cam,
    world_from_cam_to_nerfstudio,
)
from freescale_core.errors import CameraModelError, MissingInputError
from freescale_core.scene.io.assemble import RawModel
from freescale_core.scene.io.common import CorruptModelError

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                  "camera_model", "camera_angle_x", "camera_angle_y")


def _camera_from_keys(scene_id: str, d: dict, where: str, path: Path, size=None):
    """pycolmap camera from nerfstudio intrinsic keys (frame keys merged over global ones)."""
    import pycolmap

    model = str(d.get("camera_model", "OPENCV")).upper()
    try:
        w = int(d["w"]) if "w" in d else (int(size[0]) if size is not None else None)
        h = int(d["h"]) if "h" in d else (int(size[1]) if size is not None else None)
        if w is None or h is None:
            raise KeyError("w/h")
        if "fl_x" in d:
            fx = float(d["fl_x"])
            fy = float(d.get("fl_y", fx))
        elif "camera_angle_x" in d:  # instant-ngp / Blender style
            fx = 0.5 * w / np.tan(0.5 * float(d["camera_angle_x"]))
            fy = 0.5 * h / np.tan(0.5 * float(d["camera_angle_y"])) if "camera_angle_y" in d \
                else fx
        else:
            raise KeyError("fl_x")
        cx, cy = float(d.get("cx", w / 2.0)), float(d.get("cy", h / 2.0))
        k = [float(d.get(f"k{i}", 0.0)) for i in (1, 2, 3, 4)]
        p = [float(d.get(f"p{i}", 0.0)) for i in (1, 2)]
    except KeyError as e:
        raise CorruptModelError(scene_id, f"{where}: missing intrinsic {e.args[0]!r} (needs "
                                "fl_x, w, h at the top level or in the frame)", path) from None
    except (TypeError, ValueError) as e:
        raise CorruptModelError(scene_id, f"{where}: bad intrinsic value ({e})", path) from None
    if model in ("OPENCV", "PERSPECTIVE"):
        if k[3] != 0.0:
            raise CameraModelError(
                scene_id, f"{where}: OPENCV camera with k4={k[3]} (nerfstudio's polynomial k4 "
                "has no COLMAP equivalent)", path)
        if k[2] != 0.0:
            name, params = "FULL_OPENCV", [fx, fy, cx, cy, k[0], k[1], p[0], p[1], k[2], 0, 0, 0]
        else:
            name, params = "OPENCV", [fx, fy, cx, cy, k[0], k[1], p[0], p[1]]
    elif model in ("OPENCV_FISHEYE", "FISHEYE"):
        name, params = "OPENCV_FISHEYE", [fx, fy, cx, cy, *k]
    elif model in ("PINHOLE", "SIMPLE_PINHOLE"):
        name, params = "PINHOLE", [fx, fy, cx, cy]
    else:
        raise CameraModelError(
            scene_id, f"{where}: unsupported camera_model {model!r} (expected OPENCV, "
            "OPENCV_FISHEYE or PINHOLE)", path)
    return pycolmap.Camera(model=name, width=w, height=h, params=np.asarray(params, np.float64))


def _frame_image_name(file_path: str, downscale: int | None, default: str = "images") -> str:
    """Frame ``file_path`` (relative) to the image name read, in ``images_<d>/`` if asked
    (``mask_path``: ``masks_<d>/``; a bare name goes to ``<default>_<d>/``)."""
    p = PurePosixPath(str(file_path).replace("\\", "/"))
    parts = [q for q in p.parts if q != "."]
    p = PurePosixPath(*parts)
    if downscale and downscale > 1:
        parent = p.parent
        p = parent.parent / f"{parent.name}_{downscale}" / p.name if parent.name else \
            PurePosixPath(f"{default}_{downscale}") / p.name
    return p.as_posix()


def _with_ext(root: Path, name: str) -> str:
    """Blender / instant-ngp files may omit the extension (``./train/r_0``): add the one
    that exists."""
    if PurePosixPath(name).suffix or (root / name).is_file():
        return name
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG"):
        if (root / (name + ext)).is_file():
            return name + ext
    return name


def read_transforms_raw(scene_id: str, path: Path, downscale: int | None = None,
                        allow_outside: bool = False, read_masks: bool = True) -> RawModel:
    """Read ``transforms.json`` into a :class:`RawModel` (poses in the original world).

    Args:
        path: the transforms.json file.
        downscale: read frames from ``<folder>_<d>/`` (e.g. ``images_4/``); intrinsics are
            rescaled later to the actual image size.
        allow_outside: let ``file_path`` / ``ply_file_path`` point outside the scene folder
            (``..`` or absolute paths); refused by default (:class:`UnsafePathError`).
        read_masks: read ``mask_path`` (False: ``ingest.masks=ignore``).
    """
    from freescale_core.scene.io.common import inside_scene

    path = Path(path)
    root = path.parent
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise MissingInputError(scene_id, "transforms.json is missing", path) from None
    except ValueError as e:
        raise CorruptModelError(scene_id, f"transforms.json is not valid JSON ({e})", path) from e
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise CorruptModelError(scene_id, "transforms.json has no 'frames' list", path)
    applied = meta.get("applied_transform")
    if applied is not None:
        applied = np.asarray(applied, dtype=np.float64)
    glob = {k: meta[k] for k in INTRINSIC_KEYS if k in meta}
    warn: list[str] = []
    ngp = "aabb_scale" in meta or any(isinstance(f, dict) and "sharpness" in f for f in frames)
    if ngp:
        # instant-ngp writes every frame it was given; a capture pruned afterwards lists
        # images that are gone: skip them, say how many (an error for nerfstudio files)
        absent = [i for i, f in enumerate(frames) if isinstance(f, dict) and "file_path" in f
                  and not (root / _with_ext(root, _frame_image_name(f["file_path"],
                                                                    downscale))).is_file()]
        if absent:
            warn.append(f"{len(absent)} of {len(frames)} frames list an image that is absent "
                        f"and were skipped, first {[frames[i]['file_path'] for i in absent[:5]]}")
            frames = [f for i, f in enumerate(frames) if i not in set(absent)]
        n_sharp = sum("sharpness" in f for f in frames if isinstance(f, dict))
        if n_sharp:
            warn.append(f"per-frame 'sharpness' of {n_sharp} frames ignored (every listed "
                        "frame is used)")
    names, poses, cams, masks = [], [], [], []
    cam_cache: dict[str, object] = {}
    for i, fr in enumerate(frames):
        where = f"frame {i}"
        if "file_path" not in fr or "transform_matrix" not in fr:
            raise CorruptModelError(scene_id, f"{where}: needs 'file_path' and "
                                    "'transform_matrix'", path)
        name = _with_ext(root, _frame_image_name(fr["file_path"], downscale))
        where = f"frame {i} ({fr['file_path']})"
        inside_scene(scene_id, root, name, f"frame {i}: file_path", path, allow_outside)
        d = dict(glob, **{k: fr[k] for k in INTRINSIC_KEYS if k in fr})
        key = json.dumps(d, sort_keys=True)
        if key not in cam_cache:
            size = None
            if "w" not in d or "h" not in d:
                from freescale_core.scene.io.common import header_size

                size = header_size(scene_id, root / name)
            cam_cache[key] = _camera_from_keys(scene_id, d, where, path, size)
        try:
            tm = np.asarray(fr["transform_matrix"], dtype=np.float64)
            world_from_cam = nerfstudio_to_world_from_cam(tm, applied)
        except (ValueError, TypeError) as e:
            raise CorruptModelError(scene_id, f"{where}: bad transform_matrix ({e})",
                                    path) from e
        if read_masks and fr.get("mask_path"):  # nerfstudio: relative to the json, masks_<d>/ with downscale
            mname = _frame_image_name(fr["mask_path"], downscale, "masks")
            masks.append(inside_scene(scene_id, root, mname, f"frame {i}: mask_path", path,
                                      allow_outside))
        else:
            masks.append(None)
        names.append(name)
        poses.append(invert_pose(world_from_cam) if np.isfinite(world_from_cam).all()
                     else np.full((4, 4), np.nan))
        cams.append(cam_cache[key])

    xyz = np.zeros((0, 3))
    rgb = np.zeros((0, 3), np.uint8)
    extras: dict = {"transforms_json": str(path), "n_frames": len(frames)}
    ply_rel = meta.get("ply_file_path")
    if ply_rel:
        from freescale_core.scene.ply import read_ply_points

        ply_path = inside_scene(scene_id, root, ply_rel, "ply_file_path", path, allow_outside)
        if not ply_path.is_file():
            raise MissingInputError(scene_id, "ply_file_path of transforms.json does not exist",
                                    ply_path)
        xyz, rgb = read_ply_points(ply_path, scene_id)
        if applied is not None:
            A = np.eye(4)
            A[: applied.shape[0], :] = applied
            A_inv = np.linalg.inv(A)
            xyz = xyz @ A_inv[:3, :3].T + A_inv[:3, 3]
        extras["ply_file_path"] = str(ply_path)
    if applied is not None:
        extras["applied_transform"] = applied.tolist()
    if "aabb_scale" in meta:
        try:
            a = float(meta["aabb_scale"])
            sc = float(meta.get("scale", 0.33))
            off = float(np.mean(np.asarray(meta.get("offset", [0.5, 0.5, 0.5]), np.float64)))
        except (TypeError, ValueError) as e:
            raise CorruptModelError(scene_id, f"bad aabb_scale / scale / offset ({e})",
                                    path) from None
        if applied is None and a > 0 and sc > 0:
            # instant-ngp's box is [0.5 - a/2, 0.5 + a/2]^3 in its space, x_ngp = x * scale
            # + offset: in the file's world a cube of half-size a / (2 scale)
            centre, half = (0.5 - off) / sc, a / (2.0 * sc)
            extras["aabb_box"] = ([centre - half] * 3, [centre + half] * 3)
            warn.append(f"aabb_scale {a:g}: used only to bound the random initial points when "
                        f"there are no sparse points (a cube of half-size {half:.3g}), not to "
                        "crop the scene")
    mask_paths = None
    n_masked = sum(m is not None for m in masks)
    if n_masked:
        if n_masked < len(masks):
            from freescale_core.errors import MaskError

            first = [frames[i]["file_path"] for i, m in enumerate(masks) if m is None][:5]
            raise MaskError(
                scene_id, f"partly masked capture: {len(masks) - n_masked} of {len(masks)} "
                f"frames have no mask_path (first {first}); give every frame a mask_path, or "
                "set ingest.masks=ignore to train on every pixel", path)
        mask_paths = masks
    if warn:
        extras["warnings"] = warn
    folders = sorted({str(PurePosixPath(n).parent) if str(PurePosixPath(n).parent) != "."
                      else "" for n in names})
    return RawModel(
        names=names, cam_from_world=np.stack(poses) if poses else np.zeros((0, 4, 4)),
        cameras=cams, points_xyz=xyz, points_rgb=rgb, images_dir=root, pose_file=path,
        camera_file=path, source_format="nerfstudio", capture_order=np.arange(len(names)),
        model_names=list(names), count_folders=folders, stamp_files=[path], extras=extras,
        mask_paths=mask_paths, mask_source="mask_path" if mask_paths else "",
    )


# --------------------------------------------------------------------------- writer
def camera_to_keys(camera) -> dict:
    """nerfstudio intrinsic keys of a pycolmap camera (as ns-process-data writes them)."""
    p = [float(v) for v in camera.params]
    m = camera.model.name
    out = {"w": int(camera.width), "h": int(camera.height)}
    if m == "SIMPLE_PINHOLE":
        out.update(fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2], k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    elif m == "PINHOLE":
        out.update(fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3], k1=0.0, k2=0.0, p1=0.0, p2=0.0)
    elif m == "SIMPLE_RADIAL":
        out.update(fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2], k1=p[3], k2=0.0, p1=0.0, p2=0.0)
    elif m == "RADIAL":
        out.update(fl_x=p[0], fl_y=p[0], cx=p[1], cy=p[2], k1=p[3], k2=p[4], p1=0.0, p2=0.0)
    elif m == "OPENCV":
        out.update(fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3], k1=p[4], k2=p[5], p1=p[6], p2=p[7])
    elif m == "OPENCV_FISHEYE":
        out.update(fl_x=p[0], fl_y=p[1], cx=p[2], cy=p[3], k1=p[4], k2=p[5], k3=p[6], k4=p[7])
        out["camera_model"] = "OPENCV_FISHEYE"
        return out
    else:
        raise ValueError(f"camera model {m} has no nerfstudio equivalent")
    out["camera_model"] = "OPENCV"
    return out


def default_applied_transform() -> np.ndarray:
    """``[3, 4]`` world transform ns-process-data applies (swap y/z, flip the new z)."""
    A = np.eye(4)[:3, :]
    A = A[[0, 2, 1], :]
    A[2, :] *= -1
    return A


def transforms_dict(names: list[str], world_from_cam: np.ndarray, cameras: list,
                    applied_transform: np.ndarray | None = None, image_prefix: str = "images/",
                    ply_file_path: str | None = None) -> dict:
    """A transforms.json dict for pinhole or OpenCV-distorted cameras.

    Args:
        names: ``N`` image names (``file_path`` = ``image_prefix + name``).
        world_from_cam: ``[N, 4, 4]`` OpenCV axes, original world.
        cameras: ``N`` pycolmap cameras; written once at the top level when all are equal.
        applied_transform: optional ``[3, 4]`` world transform applied to poses (and expected
            to have been applied to the points of ``ply_file_path``).
    """
    keys = [camera_to_keys(c) for c in cameras]
    shared = all(k == keys[0] for k in keys)
    out: dict = dict(keys[0]) if shared else {}
    frames = []
    for i, name in enumerate(names):
        tm = world_from_cam_to_nerfstudio(world_from_cam[i], applied_transform)
        fr = {"file_path": f"{image_prefix}{name}", "transform_matrix": tm.tolist()}
        if not shared:
            fr.update(keys[i])
        frames.append(fr)
    out["frames"] = frames
    if applied_transform is not None:
        out["applied_transform"] = np.asarray(applied_transform)[:3, :].tolist()
    if ply_file_path is not None:
        out["ply_file_path"] = ply_file_path
    return out


__all__ = ["read_transforms_raw", "transforms_dict", "camera_to_keys",
           "default_applied_transform", "CV_FROM_GL"]
