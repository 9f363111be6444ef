"""Lens models: which cameras are pinhole, and undistortion / resizing into cached folders.

Every later stage (METHOD.md stages 1-10) assumes pinhole images. Cameras with lens distortion
are undistorted here once, with COLMAP's own undistorter (pycolmap), so the undistorted images
and intrinsics are exactly what COLMAP would produce for the same model.
"""

from __future__ import annotations

import contextlib
import shutil
from pathlib import Path

import numpy as np

# Models whose image formation is a pinhole projection followed by a polynomial / division
# distortion: with all distortion parameters zero they *are* pinhole cameras.
PINHOLE_MODELS = frozenset({"PINHOLE", "SIMPLE_PINHOLE"})
ZERO_IS_PINHOLE = frozenset(
    {"SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "SIMPLE_DIVISION", "DIVISION", "FOV"}
)


@contextlib.contextmanager
def quiet_colmap(level: int = 1):
    """Silence pycolmap's INFO log lines (per image) for the duration of a call."""
    import pycolmap

    old = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(old, level)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old


def known_model_names() -> list[str]:
    """Camera model names pycolmap knows (COLMAP's list)."""
    import pycolmap

    return [n for n in pycolmap.CameraModelId.__members__ if n != "INVALID"]


def is_pinhole(camera) -> bool:
    """True when a pycolmap camera has no lens distortion (usable as is)."""
    name = camera.model.name
    if name in PINHOLE_MODELS:
        return True
    if name in ZERO_IS_PINHOLE:
        extra = np.asarray(camera.params)[list(camera.extra_params_idxs())]
        return bool(np.all(extra == 0.0))
    return False


def can_undistort(camera) -> bool:
    """True for perspective models COLMAP's undistorter can map to a pinhole camera."""
    return not camera.is_spherical()


def pinhole_intrinsics(camera) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of a pycolmap camera's pinhole part (pixels)."""
    return (float(camera.focal_length_x), float(camera.focal_length_y),
            float(camera.principal_point_x), float(camera.principal_point_y))


def undistort_into(out_dir: Path, names: list[str], cam_from_world: np.ndarray, cameras: list,
                   images_dir: Path, max_image_size: int | None = None) -> dict:
    """Undistort images into ``out_dir/images/<name>`` with pycolmap; return their intrinsics.

    Args:
        out_dir: an empty folder (the cache builder's temporary folder).
        names: ``N`` image names relative to ``images_dir``.
        cam_from_world: ``[N, 4, 4]`` poses (the undistorter needs registered images; poses
            are unchanged by undistortion).
        cameras: ``N`` pycolmap cameras (distorted models), sized like the images on disk.
        images_dir: folder of the distorted images.
        max_image_size: optional cap on the undistorted image's longer side.
    Returns:
        Manifest body: ``files`` (relative paths) and ``intrinsics`` ``{name: [fx, fy, cx,
        cy, w, h]}`` of the pinhole cameras of the undistorted images.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    for i, (name, cam) in enumerate(zip(names, cameras)):
        key = (cam.model.name, int(cam.width), int(cam.height), tuple(np.asarray(cam.params)))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            c = pycolmap.Camera(model=cam.model.name, width=int(cam.width),
                                height=int(cam.height), params=np.asarray(cam.params),
                                camera_id=cam_ids[key])
            rec.add_camera_with_trivial_rig(c)
        img = pycolmap.Image(name=name, camera_id=cam_ids[key], image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(cam_from_world[i, :3, :4]))
    model_in = out_dir / "_model_in"
    model_in.mkdir()
    rec.write(str(model_in))
    opts = pycolmap.UndistortCameraOptions()
    if max_image_size is not None:
        opts.max_image_size = int(max_image_size)
    work = out_dir / "_undistort"
    with quiet_colmap():
        pycolmap.undistort_images(str(work), str(model_in), str(images_dir),
                                  image_names=list(names), undistort_options=opts)
    shutil.move(str(work / "images"), str(out_dir / "images"))
    ud = pycolmap.Reconstruction(str(work / "sparse"))
    intr = {}
    for img in ud.images.values():
        cam = ud.cameras[img.camera_id]
        intr[img.name] = [*pinhole_intrinsics(cam), int(cam.width), int(cam.height)]
    shutil.rmtree(work)
    shutil.rmtree(model_in)
    missing = [n for n in names if n not in intr or not (out_dir / "images" / n).is_file()]
    if missing:
        raise RuntimeError(f"pycolmap did not undistort {len(missing)} images, first {missing[:3]}")
    return {"files": [f"images/{n}" for n in names], "intrinsics": intr}


def resize_into(out_dir: Path, names: list[str], src_paths: list[Path],
                intrinsics: np.ndarray, max_image_size: int) -> dict:
    """Resize pinhole images so their longer side is at most ``max_image_size`` pixels.

    Args:
        intrinsics: ``[N, 6]`` (fx, fy, cx, cy, w, h) of the source images.
    Returns:
        Manifest body like :func:`undistort_into`. Intrinsics scale with the image edges
        (pixel-centre convention (0.5, 0.5), so scaling by the size ratio is exact).
    """
    import cv2

    intr = {}
    for name, src, (fx, fy, cx, cy, w, h) in zip(names, src_paths, intrinsics):
        w, h = int(w), int(h)
        s = min(1.0, max_image_size / max(w, h))
        nw, nh = max(1, int(round(w * s))), max(1, int(round(h * s)))
        dst = out_dir / "images" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        img = cv2.imdecode(np.fromfile(src, np.uint8), cv2.IMREAD_UNCHANGED)
        if (nw, nh) != (w, h):
            img = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_AREA)
        params = [cv2.IMWRITE_JPEG_QUALITY, 95] if dst.suffix.lower() in (".jpg", ".jpeg") else []
        ok, buf = cv2.imencode(dst.suffix, img, params)
        if not ok:
            raise RuntimeError(f"cannot encode resized image {dst}")
        buf.tofile(dst)
        sx, sy = nw / w, nh / h
        intr[name] = [fx * sx, fy * sy, cx * sx, cy * sy, nw, nh]
    return {"files": [f"images/{n}" for n in names], "intrinsics": intr}
