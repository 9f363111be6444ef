"""Bad inputs: each broken copy of a real scene raises the right SceneError naming scene + file.

The paper pre-filters its scenes (count mismatch, unreadable images, no model, too few
registered views, ...); each case here is a small real scene (kermit, 9 images, 1 MB) copied
to tmp_path and broken in one way.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from freescale_core.errors import (
    CameraModelError,
    CorruptImageError,
    DegenerateSceneError,
    ImageCountMismatchError,
    MissingInputError,
    SceneError,
)
from freescale_core.scene.io import CorruptModelError, MissingImageError, load_scene
from freescale_core.scene.describe import inspect_scene
from schemas.ingest import IngestConfig
from tests.conftest import real_scene_dir

pycolmap = pytest.importorskip("pycolmap")

SCENE = "kermit"


@pytest.fixture
def scene(tmp_path) -> Path:
    import os

    out = tmp_path / "brokenscene"
    shutil.copytree(real_scene_dir(SCENE), out, ignore=shutil.ignore_patterns(".freescale_cache"))
    for p in [out, *out.rglob("*")]:  # the shared files are read-only
        os.chmod(p, p.stat().st_mode | 0o200)
    return out


def load(d: Path, **kw):
    return load_scene(d, cache_dir=d.parent / "cache", **kw)


def check_msg(err: SceneError, *parts: str) -> None:
    msg = str(err)
    assert err.scene == "brokenscene" and "brokenscene" in msg
    for p in parts:
        assert p in msg, f"{p!r} not in {msg!r}"


def test_corrupt_jpeg_garbage(scene):
    bad = scene / "images" / "kermit003.jpg"
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(CorruptImageError) as e:
        load(scene)
    check_msg(e.value, "kermit003.jpg")
    assert e.value.path == str(bad)


def test_truncated_jpeg(scene):
    bad = scene / "images" / "kermit005.jpg"
    data = bad.read_bytes()
    bad.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(CorruptImageError) as e:
        load(scene)
    check_msg(e.value, "kermit005.jpg")


def test_missing_image(scene):
    (scene / "images" / "kermit007.jpg").unlink()
    with pytest.raises(MissingImageError) as e:
        load(scene)
    check_msg(e.value, "kermit007.jpg", "9 images in the camera model", "8 image files")
    # a missing image is both a count mismatch and a missing input
    assert isinstance(e.value, ImageCountMismatchError)
    assert isinstance(e.value, MissingInputError)


def test_count_mismatch_extra_image(scene):
    shutil.copy(scene / "images" / "kermit000.jpg", scene / "images" / "kermit099.jpg")
    with pytest.raises(ImageCountMismatchError) as e:
        load(scene)
    check_msg(e.value, "kermit099.jpg", "9 images in the camera model", "10 image files")
    assert not isinstance(e.value, MissingInputError)


def test_missing_sparse_folder(scene):
    shutil.rmtree(scene / "sparse")
    with pytest.raises(MissingInputError) as e:
        load(scene)
    check_msg(e.value, "sparse")
    assert e.value.path == str(scene / "sparse")
    with pytest.raises(MissingInputError):
        inspect_scene(scene)
    # asked for explicitly, the same folder is an image-only scene (SfM would run)
    info = inspect_scene(scene, cfg=IngestConfig(format="images"))
    assert info["format"] == "images" and info["n_images"] == 9 and info["needs_sfm"]


def test_empty_sparse_and_incomplete_model(scene):
    (scene / "sparse" / "0" / "points3D.txt").unlink()
    with pytest.raises(MissingInputError) as e:
        load(scene)
    check_msg(e.value, "points3D")
    shutil.rmtree(scene / "sparse" / "0")
    with pytest.raises(MissingInputError) as e:
        load(scene)
    check_msg(e.value, "sparse")


def test_missing_images_folder(scene):
    shutil.rmtree(scene / "images")
    with pytest.raises(MissingInputError) as e:
        load(scene)
    check_msg(e.value, "images")


def test_unknown_camera_model(scene):
    cams = scene / "sparse" / "0" / "cameras.txt"
    cams.write_text(cams.read_text().replace("\n4 RADIAL", "\n4 FANCY_LENS"))
    with pytest.raises(CameraModelError) as e:
        load(scene)
    check_msg(e.value, "FANCY_LENS", "camera 4", "cameras.txt")
    with pytest.raises(CameraModelError):
        inspect_scene(scene)


def test_unknown_camera_model_binary(scene):
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    model = scene / "sparse" / "0"
    for f in model.iterdir():
        f.unlink()
    rec.write(str(model))
    data = bytearray((model / "cameras.bin").read_bytes())
    data[8 + 4: 8 + 8] = (99).to_bytes(4, "little")  # first camera's model id
    (model / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(CameraModelError) as e:
        load(scene)
    check_msg(e.value, "unknown camera model id 99", "cameras.bin")


def test_wrong_parameter_count(scene):
    cams = scene / "sparse" / "0" / "cameras.txt"
    cams.write_text(cams.read_text().replace("\n2 RADIAL", "\n2 OPENCV"))
    with pytest.raises(CameraModelError) as e:
        load(scene)
    check_msg(e.value, "camera 2", "takes 8 parameters", "cameras.txt")


def test_nan_pose_text(scene):
    f = scene / "sparse" / "0" / "images.txt"
    lines = f.read_text().split("\n")
    for i, ln in enumerate(lines):
        if ln.endswith("kermit002.jpg"):
            parts = ln.split()
            parts[5] = "nan"
            lines[i] = " ".join(parts)
    f.write_text("\n".join(lines))
    with pytest.raises(DegenerateSceneError) as e:
        load(scene)
    check_msg(e.value, "kermit002.jpg", "non-finite", "images.txt")


def test_nan_pose_binary(scene):
    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    img = next(im for im in rec.images.values() if im.name == "kermit002.jpg")
    fr = rec.frames[img.frame_id]
    M = fr.rig_from_world.matrix()
    M[0, 3] = np.nan
    fr.rig_from_world = pycolmap.Rigid3d(M)
    for f in model.iterdir():
        f.unlink()
    rec.write(str(model))
    with pytest.raises(DegenerateSceneError) as e:
        load(scene)
    check_msg(e.value, "kermit002.jpg", "non-finite", "images.bin")


def test_too_few_registered(scene):
    model = scene / "sparse" / "0"
    rec = pycolmap.Reconstruction(str(model))
    for fid in sorted(rec.reg_frame_ids())[2:]:
        rec.deregister_frame(fid)
    for f in model.iterdir():
        f.unlink()
    rec.write(str(model))
    with pytest.raises(DegenerateSceneError) as e:
        load(scene)
    check_msg(e.value, "only 2 registered views", "at least 3", "images.bin")
    # the threshold is a config field
    with pytest.raises(ImageCountMismatchError):
        load(scene, cfg=IngestConfig(min_registered=2))  # then 7 images are not in the model


def test_image_size_not_a_downscale(scene):
    import cv2

    p = scene / "images" / "kermit001.jpg"
    img = cv2.imread(str(p))
    cv2.imwrite(str(p), img[:, :400])  # 400x480: another aspect ratio
    with pytest.raises(CameraModelError) as e:
        load(scene)
    check_msg(e.value, "kermit001.jpg", "400x480", "640x480")


def test_garbage_model_file(scene):
    f = scene / "sparse" / "0" / "images.txt"
    f.write_text("# header\nthis is not a pose line\n")
    with pytest.raises(CorruptModelError) as e:
        load(scene)
    check_msg(e.value, "images.txt")


def test_nonexistent_path(tmp_path):
    with pytest.raises(MissingInputError) as e:
        load_scene(tmp_path / "nope")
    assert "nope" in str(e.value)


@pytest.mark.parametrize("size", [(8, 6), (1280, 960)])
def test_one_image_of_another_scale_is_an_outlier_not_a_downscale(scene, size):
    """One thumbnail (or one full-size file) among the images: named, not a rescale of every
    camera to ~8x6 px (issue 12 #11)."""
    import cv2

    p = scene / "images" / "kermit005.jpg"
    cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), size, interpolation=cv2.INTER_AREA))
    with pytest.raises(CameraModelError) as e:
        load(scene)
    check_msg(e.value, "kermit005.jpg", "outlier", f"{size[0]}x{size[1]}", "640x480")


def test_every_image_downscaled_alike_is_still_a_downscale(scene):
    import cv2

    for p in (scene / "images").iterdir():
        cv2.imwrite(str(p), cv2.resize(cv2.imread(str(p)), (320, 240)))
    s = load(scene)
    assert abs(int(s.cameras.width[0]) - 320) <= 2  # (undistorted: a pixel more or less)


def test_a_track_naming_an_absent_image_is_a_corrupt_model_naming_points3d(tmp_path):
    """pycolmap raises IndexError('Image with ID 999 does not exist'); the scene fails naming
    the scene and points3D.txt (was: an IndexError traceback)."""
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp_path / "trk", n_views=6, width=32, height=24, seed=0)
    p = d / "sparse" / "0" / "points3D.txt"
    lines = p.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    f = lines[k].split()
    f[8] = "999"  # the first track element's IMAGE_ID
    lines[k] = " ".join(f)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(CorruptModelError) as e:
        load_scene(d, cache_dir=tmp_path / "cache")
    assert e.value.scene == "trk" and "999" in str(e.value) and str(p) in str(e.value)
