"""transforms.json (nerfstudio / DL3DV) ingestion against fixtures made from real scenes.

Each fixture converts a shared COLMAP scene to a nerfstudio dataset the way ns-process-data
does (OpenGL c2w, applied_transform, ASCII sparse_pc.ply in the applied world); reading it
back must give the COLMAP poses (1e-9), points, intrinsics and undistorted images.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from freescale_core.geometry.cameras import invert_pose
from freescale_core.errors import CameraModelError, DegenerateSceneError
from freescale_core.scene.describe import inspect_scene
from freescale_core.scene.io import MissingImageError, load_scene
from freescale_core.scene.io.nerfstudio import default_applied_transform, transforms_dict
from freescale_core.scene.ply import write_ply_points
from schemas.ingest import IngestConfig
from tests.conftest import real_scene_dir

pycolmap = pytest.importorskip("pycolmap")


def make_ns_scene(name: str, dst: Path, applied: bool = True, reverse: bool = True) -> Path:
    """A nerfstudio dataset (images/, transforms.json, sparse_pc.ply) from a real scene."""
    src = real_scene_dir(name)
    out = dst / f"{name}_ns"
    shutil.copytree(src / "images", out / "images")
    rec = pycolmap.Reconstruction(str(src / "sparse" / "0"))
    imgs = sorted(rec.images.values(), key=lambda im: im.name, reverse=reverse)
    names = [im.name for im in imgs]
    wfc = []
    for im in imgs:
        T = np.eye(4)
        T[:3] = im.cam_from_world().matrix()
        wfc.append(invert_pose(T))
    cams = [rec.cameras[im.camera_id] for im in imgs]
    A = default_applied_transform() if applied else None
    meta = transforms_dict(names, np.stack(wfc), cams, A, ply_file_path="sparse_pc.ply")
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    rgb = np.array([p.color for p in rec.points3D.values()], np.uint8)
    if A is not None:
        xyz = xyz @ A[:3, :3].T + A[:3, 3]
    write_ply_points(out / "sparse_pc.ply", xyz, rgb, ascii=True)
    (out / "transforms.json").write_text(json.dumps(meta, indent=2))
    return out


def colmap_reference(name: str):
    rec = pycolmap.Reconstruction(str(real_scene_dir(name) / "sparse" / "0"))
    by_name = {}
    for im in rec.images.values():
        T = np.eye(4)
        T[:3] = im.cam_from_world().matrix()
        by_name[im.name] = (invert_pose(T), rec.cameras[im.camera_id])
    xyz = np.array([p.xyz for p in rec.points3D.values()])
    return by_name, xyz


@pytest.mark.parametrize("applied", [True, False])
def test_pinhole_round_trip(tmp_path, applied):
    d = make_ns_scene("buddha", tmp_path, applied=applied)
    s = load_scene(d)
    ref, xyz = colmap_reference("buddha")
    assert s.source_format == "nerfstudio" and len(s) == 13 and not s.undistorted
    assert s.camera_models == ["OPENCV"] * 13  # zero distortion: used as pinhole, no cache
    # frames were written in reverse name order: capture order is frame order
    assert s.image_names == ["images/" + n for n in sorted(ref, reverse=True)]
    assert np.array_equal(s.capture_order, np.arange(13))
    for i, nm in enumerate(s.image_names):
        wfc, cam = ref[nm.removeprefix("images/")]
        assert np.abs(s.cameras.world_from_cam[i] - wfc).max() < 1e-9
        assert np.allclose([s.cameras.fx[i], s.cameras.fy[i], s.cameras.cx[i], s.cameras.cy[i]],
                           [cam.focal_length_x, cam.focal_length_y, cam.principal_point_x,
                            cam.principal_point_y], atol=1e-12)
        assert s.image_paths[i] == d / nm
    # points come back into the COLMAP world (float32 ASCII precision)
    assert np.allclose(s.points_xyz, xyz, atol=1e-5 * np.abs(xyz).max())
    assert ("applied_transform" in s.extras) == applied


def test_distorted_per_frame_intrinsics_match_colmap_path(tmp_path):
    """kermit: 9 RADIAL cameras -> per-frame OPENCV intrinsics; the undistorted cameras and
    images equal those of the COLMAP reader (same undistorter)."""
    d = make_ns_scene("kermit", tmp_path)
    meta = json.loads((d / "transforms.json").read_text())
    assert "fl_x" not in meta and "k1" in meta["frames"][0]  # per-frame intrinsics
    s = load_scene(d, cache_dir=tmp_path / "cache_ns")
    c = load_scene(real_scene_dir("kermit"), cache_dir=tmp_path / "cache_colmap")
    assert s.undistorted and s.camera_models == ["OPENCV"] * 9
    order = [c.image_names.index(n.split("/", 1)[1]) for n in s.image_names]
    for i, j in enumerate(order):
        assert np.abs(s.cameras.world_from_cam[i] - c.cameras.world_from_cam[j]).max() < 1e-9
        for f in ("fx", "fy", "cx", "cy", "width", "height"):
            assert np.isclose(getattr(s.cameras, f)[i], getattr(c.cameras, f)[j], atol=1e-9), f
    a = s.load_image(0).astype(int)
    b = c.load_image(order[0]).astype(int)
    assert a.shape == b.shape and np.abs(a - b).mean() < 0.5


def test_global_intrinsics_and_downscale(tmp_path):
    import cv2

    d = make_ns_scene("llff_fern", tmp_path)
    meta = json.loads((d / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and "fl_x" in meta  # one shared camera
    (d / "images_2").mkdir()
    for p in (d / "images").iterdir():
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        h, w = img.shape[:2]
        cv2.imwrite(str(d / "images_2" / p.name), cv2.resize(img, (w // 2, h // 2)))
    full = load_scene(d, cache_dir=tmp_path / "c1")
    half = load_scene(d, cache_dir=tmp_path / "c2", cfg=IngestConfig(downscale=2))
    assert half.image_names[0].startswith("images_2/")
    assert half.extras["n_rescaled_cameras"] == 20
    assert np.allclose(half.cameras.world_from_cam, full.cameras.world_from_cam)
    # undistorted focal length halves with the image (pycolmap rescales the raw camera)
    assert np.allclose(half.cameras.fx / full.cameras.fx, 0.5, atol=0.01)


def test_inspect_transforms(tmp_path):
    d = make_ns_scene("kermit", tmp_path)
    info = inspect_scene(d)
    assert info["format"] == "nerfstudio" and info["n_images"] == 9
    assert info["camera_models"] == ["OPENCV"] and info["needs_undistortion"]
    assert info["n_points"] == 1935


def test_transforms_json_file_path_accepted(tmp_path):
    d = make_ns_scene("buddha", tmp_path)
    s = load_scene(d / "transforms.json")
    assert s.scene_id == "buddha_ns" and len(s) == 13


def _edit(d: Path, fn) -> None:
    meta = json.loads((d / "transforms.json").read_text())
    fn(meta)
    (d / "transforms.json").write_text(json.dumps(meta))


def test_nan_transform_names_frame(tmp_path):
    d = make_ns_scene("buddha", tmp_path)
    bad = None

    def f(m):
        nonlocal bad
        m["frames"][3]["transform_matrix"][0][3] = float("nan")
        bad = m["frames"][3]["file_path"]

    _edit(d, f)
    with pytest.raises(DegenerateSceneError) as e:
        load_scene(d)
    msg = str(e.value)
    assert "buddha_ns" in msg and "transforms.json" in msg and bad.split("/")[-1] in msg


def test_unknown_camera_model_and_missing_frame_image(tmp_path):
    d = make_ns_scene("buddha", tmp_path)
    _edit(d, lambda m: m["frames"][5].update(camera_model="EQUIRECTANGULAR"))
    with pytest.raises(CameraModelError, match="EQUIRECTANGULAR") as e:
        load_scene(d)
    assert "transforms.json" in str(e.value)
    _edit(d, lambda m: m["frames"][5].update(camera_model="OPENCV"))
    name = json.loads((d / "transforms.json").read_text())["frames"][0]["file_path"]
    (d / name).unlink()
    with pytest.raises(MissingImageError) as e:
        load_scene(d)
    assert "13 images in the camera model" in str(e.value) and "12 image files" in str(e.value)
    assert Path(name).name in str(e.value)


@pytest.mark.parametrize("where", ["dotdot", "absolute", "ply"])
def test_paths_outside_the_scene_folder_are_refused(tmp_path, where):
    """transforms.json may not make a scene read files outside its folder (issue 12 #7)."""
    from freescale_core.errors import UnsafePathError

    d = make_ns_scene("buddha", tmp_path)
    secret = tmp_path / "secret"
    secret.mkdir()
    first = json.loads((d / "transforms.json").read_text())["frames"][0]["file_path"]
    shutil.copy(d / first, secret / "stolen.jpg")
    shutil.copy(d / "sparse_pc.ply", secret / "pts.ply")
    target = {"dotdot": "../secret/stolen.jpg", "absolute": str(secret / "stolen.jpg"),
              "ply": "../secret/pts.ply"}[where]

    def f(m):
        if where == "ply":
            m["ply_file_path"] = target
        else:
            m["frames"][0]["file_path"] = target

    _edit(d, f)
    with pytest.raises(UnsafePathError) as e:
        load_scene(d)
    msg = str(e.value)
    assert "outside the scene folder" in msg and target in msg and "transforms.json" in msg
    assert ("ply_file_path" if where == "ply" else "frame 0") in msg
    # the explicit opt-in reads it
    if where == "ply":
        s = load_scene(d, cfg=IngestConfig(allow_outside_paths=True))
        assert len(s.points_xyz) > 0
