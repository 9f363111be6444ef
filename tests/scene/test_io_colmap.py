"""COLMAP ingestion on the shared real scenes: counts, order, undistortion cache, layouts."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from freescale_core.geometry.cameras import invert_pose
from freescale_core.errors import CameraModelError
from freescale_core.scene.describe import inspect_scene
from freescale_core.scene.io import load_scene
from freescale_core.scene.images import natural_order
from freescale_core.scene.scene import read_rgb
from schemas.ingest import IngestConfig
from tests.conftest import REAL_SCENES, real_scene_dir

pycolmap = pytest.importorskip("pycolmap")

EXPECTED = {  # scene: (registered images, camera model) from datasets/README.md
    "kermit": (9, "RADIAL"),
    "buddha": (13, "PINHOLE"),
    "llff_fern": (20, "SIMPLE_RADIAL"),
    "strecha_fountain-P11": (11, "PINHOLE"),
    "dtu_scan24": (49, "PINHOLE"),
}


def copy_scene(name: str, dst: Path) -> Path:
    """A writable copy of a shared scene (the shared files are read-only)."""
    import os

    src = real_scene_dir(name)
    out = dst / name
    shutil.copytree(src, out, ignore=shutil.ignore_patterns(".freescale_cache"))
    for p in [out, *out.rglob("*")]:
        os.chmod(p, p.stat().st_mode | 0o200)
    return out


def test_natural_order():
    names = ["img10.png", "img2.png", "IMG1.png", "img2b.png", "a/img3.png"]
    assert [names[i] for i in natural_order(names)] == \
        ["a/img3.png", "IMG1.png", "img2.png", "img2b.png", "img10.png"]


@pytest.mark.parametrize("name", REAL_SCENES)
def test_inspect_real_scenes(name):
    d = real_scene_dir(name)
    info = inspect_scene(d)
    n, model = EXPECTED[name]
    assert info["scene_id"] == name and info["format"] == "colmap"
    assert info["n_images"] == n and info["n_image_files"] == n
    assert info["camera_models"] == [model]
    assert info["needs_undistortion"] == (model not in ("PINHOLE", "SIMPLE_PINHOLE"))
    assert info["n_points"] > 200
    lo, hi = np.array(info["bounds_min"]), np.array(info["bounds_max"])
    assert np.all(hi > lo)
    json.dumps(info)  # JSON-able for `freescale inspect --json`


@pytest.mark.parametrize("name", REAL_SCENES)
def test_load_real_scenes(name, tmp_path):
    d = real_scene_dir(name)
    s = load_scene(d, cache_dir=tmp_path)
    n, model = EXPECTED[name]
    rec = pycolmap.Reconstruction(str(d / "sparse" / "0"))
    assert len(s) == n and s.scene_id == name and s.source_format == "colmap"
    assert s.camera_models == [model] * n
    assert s.undistorted == (model not in ("PINHOLE", "SIMPLE_PINHOLE"))
    assert [s.image_names[i] for i in natural_order(s.image_names)] == s.image_names
    assert np.array_equal(s.capture_order, np.arange(n))
    assert len(s.points_xyz) == rec.num_points3D() and s.points_rgb.dtype == np.uint8
    # poses are COLMAP's (world_from_cam = inverse of cam_from_world)
    by_name = {im.name: im for im in rec.images.values()}
    for i, nm in enumerate(s.image_names):
        T = np.eye(4)
        T[:3] = by_name[nm].cam_from_world().matrix()
        assert np.allclose(s.cameras.world_from_cam[i], invert_pose(T), atol=1e-12)
    # images exist, decode, and have the cameras' sizes
    for i in (0, n - 1):
        img = s.load_image(i)
        assert img.shape == (s.cameras.height[i], s.cameras.width[i], 3)
    if s.undistorted:
        assert all(str(p).startswith(str(tmp_path)) for p in s.image_paths)
    else:
        assert all(p.parent == d / "images" for p in s.image_paths)


def test_undistortion_cache_reused_and_rebuilt(tmp_path):
    d = real_scene_dir("kermit")
    s1 = load_scene(d, cache_dir=tmp_path)
    folder = tmp_path / "kermit" / "undistorted"
    assert s1.extras["cache_reused"] is False and folder.is_dir()
    mtimes = {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()}
    s2 = load_scene(d, cache_dir=tmp_path)
    assert s2.extras["cache_reused"] is True
    assert {p: p.stat().st_mtime_ns for p in folder.rglob("*") if p.is_file()} == mtimes
    assert np.array_equal(s1.cameras.fx, s2.cameras.fx)
    # a stale or half-written cache (manifest missing) is rebuilt, never used
    (folder / "_manifest.json").unlink()
    s3 = load_scene(d, cache_dir=tmp_path)
    assert s3.extras["cache_reused"] is False
    assert np.array_equal(s3.cameras.fx, s1.cameras.fx)
    # an image removed from the cache also invalidates it
    s3.image_paths[0].unlink()
    assert load_scene(d, cache_dir=tmp_path).extras["cache_reused"] is False
    # no temporary folders are left behind
    assert sorted(p.name for p in (tmp_path / "kermit").iterdir()) == ["undistorted"]


def test_default_cache_inside_scene_and_hidden_from_count_check(tmp_path):
    d = copy_scene("kermit", tmp_path)
    s = load_scene(d)
    assert (d / ".freescale_cache" / "undistorted" / "_manifest.json").is_file()
    assert s.image_paths[0].is_relative_to(d / ".freescale_cache")
    # the cache's images do not count as extra images on the next load
    assert load_scene(d).extras["cache_reused"] is True


def test_binary_model_and_layouts(tmp_path):
    """Binary sparse/0, a bare sparse/, and the model folder passed directly all agree."""
    ref = load_scene(real_scene_dir("strecha_fountain-P11"))
    d = copy_scene("strecha_fountain-P11", tmp_path)
    rec = pycolmap.Reconstruction(str(d / "sparse" / "0"))
    for f in (d / "sparse" / "0").iterdir():
        f.unlink()
    rec.write(str(d / "sparse" / "0"))  # binary
    s_bin = load_scene(d)
    assert (d / "sparse" / "0" / "images.bin").is_file()
    for f in (d / "sparse" / "0").iterdir():
        shutil.move(str(f), str(d / "sparse" / f.name))
    (d / "sparse" / "0").rmdir()
    s_sparse = load_scene(d)
    s_direct = load_scene(d / "sparse")
    for s in (s_bin, s_sparse, s_direct):
        assert s.scene_id == "strecha_fountain-P11"
        assert s.image_names == ref.image_names
        assert np.allclose(s.cameras.world_from_cam, ref.cameras.world_from_cam, atol=1e-12)
        assert np.allclose(s.cameras.fx, ref.cameras.fx)
        assert np.allclose(s.points_xyz, ref.points_xyz)


def test_max_image_size_resizes_pinhole_scene(tmp_path):
    d = real_scene_dir("strecha_fountain-P11")
    full = load_scene(d)
    small = load_scene(d, cache_dir=tmp_path, cfg=IngestConfig(max_image_size=384))
    assert (small.cameras.width[0], small.cameras.height[0]) == (384, 256)
    assert small.load_image(0).shape == (256, 384, 3)
    uv_f, _ = full.cameras.project(full.points_xyz[:100])
    uv_s, _ = small.cameras.project(full.points_xyz[:100])
    assert np.allclose(uv_s, uv_f * 0.5, atol=1e-9)
    assert "resized" in small.extras["cache_dir"]


def test_max_image_size_with_undistortion(tmp_path):
    s = load_scene(real_scene_dir("kermit"), cache_dir=tmp_path,
                   cfg=IngestConfig(max_image_size=320))
    assert s.undistorted and max(s.cameras.width.max(), s.cameras.height.max()) <= 320
    assert read_rgb(s.image_paths[0]).shape[:2] == (s.cameras.height[0], s.cameras.width[0])


def test_downscale_folder_scales_intrinsics(tmp_path):
    import cv2

    d = copy_scene("buddha", tmp_path)
    (d / "images_2").mkdir()
    for p in (d / "images").iterdir():
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        h, w = img.shape[:2]
        cv2.imwrite(str(d / "images_2" / p.name), cv2.resize(img, (w // 2, h // 2),
                                                             interpolation=cv2.INTER_AREA))
    full = load_scene(d)
    half = load_scene(d, cfg=IngestConfig(downscale=2))
    assert (half.cameras.width[0], half.cameras.height[0]) == (342, 192)
    assert half.image_paths[0].parent.name == "images_2"
    sx, sy = 342 / 684, 192 / 385
    assert np.allclose(half.cameras.fx, full.cameras.fx * sx)
    assert np.allclose(half.cameras.cy, full.cameras.cy * sy)
    assert half.extras["n_rescaled_cameras"] == 13


def test_undistort_off_rejects_distorted_model():
    with pytest.raises(CameraModelError, match="undistortion is off") as e:
        load_scene(real_scene_dir("kermit"), cfg=IngestConfig(undistort=False))
    assert "kermit" in str(e.value) and "cameras.txt" in str(e.value)


def test_read_only_scene_gets_cache_elsewhere(tmp_path):
    """A scene folder marked read-only (like ../shared/datasets) never receives a cache,
    even for root, who may write anywhere."""
    import os
    import stat

    d = copy_scene("kermit", tmp_path)
    mode = d.stat().st_mode
    os.chmod(d, mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
    try:
        s = load_scene(d)
    finally:
        os.chmod(d, mode)
    cache = Path(s.extras["cache_dir"])
    shutil.rmtree(cache.parent, ignore_errors=True)  # the temp cache root of this scene
    assert not (d / ".freescale_cache").exists()
    assert not cache.is_relative_to(d)
