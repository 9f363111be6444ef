"""A folder of images only: SfM with pycolmap on the CPU, checked against ground-truth cameras.

strecha_fountain-P11 comes with ground-truth cameras (EPFL); SfM on 8 of its images must
register them all and recover the camera centres up to a similarity (Umeyama alignment).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from freescale_core.errors import CorruptImageError, DegenerateSceneError
from freescale_core.scene.describe import inspect_scene
from freescale_core.scene.io import load_scene
from tests.conftest import real_scene_dir

pycolmap = pytest.importorskip("pycolmap")


def umeyama_residual(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Per-point residuals after the best similarity src -> dst (least squares)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    S, D = src - mu_s, dst - mu_d
    U, sig, Vt = np.linalg.svd(D.T @ S / len(src))
    E = np.eye(3)
    E[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ E @ Vt
    scale = np.trace(np.diag(sig) @ E) / (S ** 2).sum(1).mean()
    return np.linalg.norm(scale * S @ R.T + mu_d - dst, axis=1)


@pytest.mark.slow
def test_sfm_on_fountain_images(tmp_path):
    src = real_scene_dir("strecha_fountain-P11")
    folder = tmp_path / "fountain_imgs"
    folder.mkdir()
    names = [f"{i:04d}.jpg" for i in range(8)]
    for n in names:
        shutil.copy(src / "images" / n, folder / n)
    info = inspect_scene(folder)
    assert info["format"] == "images" and info["n_images"] == 8 and info["needs_sfm"]

    s = load_scene(folder, cache_dir=tmp_path / "cache")
    assert s.source_format == "images"
    assert s.extras["n_input_images"] == 8
    assert s.extras["n_registered"] == len(s) >= 7
    assert s.undistorted and len(s.points_xyz) > 500
    gt = load_scene(src)
    gt_c = gt.cameras.centers[[gt.image_names.index(n) for n in s.image_names]]
    res = umeyama_residual(s.cameras.centers, gt_c)
    extent = np.linalg.norm(gt_c - gt_c.mean(0), axis=1).max()
    assert res.max() < 0.02 * extent, (res, extent)
    # focal length close to the calibrated one (689.87 px at 768 px width)
    assert abs(np.median(s.cameras.fx) - 689.87) / 689.87 < 0.05
    # cached: a second ingest does not run SfM again
    s2 = load_scene(folder, cache_dir=tmp_path / "cache")
    assert s2.extras["sfm_cache_reused"] and np.allclose(s2.cameras.centers, s.cameras.centers)


def test_sfm_rejects_unmatchable_images(tmp_path):
    import cv2

    folder = tmp_path / "noise"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        img = cv2.GaussianBlur(rng.integers(0, 256, (96, 128, 3), dtype=np.uint8), (5, 5), 0)
        cv2.imwrite(str(folder / f"n{i}.png"), img)
    with pytest.raises(DegenerateSceneError) as e:
        load_scene(folder, cache_dir=tmp_path / "cache")
    assert "noise" in str(e.value) and "3 images" in str(e.value)


def test_sfm_input_is_checked_before_sfm(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    src = real_scene_dir("strecha_fountain-P11")
    for i in range(3):
        shutil.copy(src / "images" / f"{i:04d}.jpg", folder / f"{i:04d}.jpg")
    (folder / "0001.jpg").write_bytes(b"\xff\xd8garbage")
    with pytest.raises(CorruptImageError, match="0001.jpg"):
        load_scene(folder, cache_dir=tmp_path / "cache")
