"""Object masks at ingest: nerfstudio ``mask_path``, COLMAP ``masks/``, the naming rules,
size / missing / corrupt errors, and masks warped exactly like their images."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from freescale_core.errors import CorruptImageError, MaskError
from freescale_core.scene.io import load_scene
from freescale_core.scene.turntable import (
    render_turntable,
    turntable_spec,
    write_turntable_scene,
)
from schemas.ingest import IngestConfig

N, W, H = 6, 32, 24


@pytest.fixture(scope="module")
def truth():
    """The masks the writer renders, in capture order."""
    from freescale_core.scene.sample import SampleWorld

    spec = turntable_spec(N, W, H, 0)
    _, masks, _ = render_turntable(spec, SampleWorld(spec).cameras, 0)
    return masks


@pytest.mark.parametrize("naming", ["same", "stem_png", "name_png"])
def test_colmap_masks_folder_every_naming(tmp_path, truth, naming):
    d = write_turntable_scene(tmp_path / "tt", N, W, H, fmt="colmap", mask_naming=naming,
                              n_points=200)
    s = load_scene(d, cache_dir=tmp_path / "cache")
    assert s.has_masks and s.extras["masks"] == "masks/"
    for i in range(N):
        m = s.load_mask(i)
        assert m.dtype == bool and m.shape == (H, W)
        assert np.array_equal(m, truth[i])
    assert 0.05 < truth.mean() < 0.6  # the object is neither absent nor everything
    sub = s.subset([1, 3])
    assert np.array_equal(sub.load_mask(1), truth[3])
    # ingest.masks=ignore reads none
    assert not load_scene(d, cache_dir=tmp_path / "c2", cfg=IngestConfig(masks="ignore")).has_masks


def test_nerfstudio_mask_path(tmp_path, truth):
    d = write_turntable_scene(tmp_path / "ns", N, W, H, fmt="nerfstudio", mask_naming="name_png")
    s = load_scene(d, cache_dir=tmp_path / "cache")
    assert s.has_masks and s.extras["masks"] == "mask_path"
    assert all(np.array_equal(s.load_mask(i), truth[i]) for i in range(N))
    assert not load_scene(d, cache_dir=tmp_path / "c2", cfg=IngestConfig(masks="ignore")).has_masks
    # no mask_path at all: no masks, no error
    meta = json.loads((d / "transforms.json").read_text())
    for fr in meta["frames"]:
        fr.pop("mask_path")
    (d / "transforms.json").write_text(json.dumps(meta))
    assert not load_scene(d, cache_dir=tmp_path / "c3").has_masks


def test_masks_kept_among_the_images_are_not_extra_images(tmp_path, truth):
    d = write_turntable_scene(tmp_path / "ns", N, W, H, fmt="nerfstudio")
    meta = json.loads((d / "transforms.json").read_text())
    for fr in meta["frames"]:
        name = fr["mask_path"].split("/")[-1]
        (d / "masks" / name).rename(d / "images" / f"mask_{name}")
        fr["mask_path"] = f"images/mask_{name}"
    (d / "transforms.json").write_text(json.dumps(meta))
    s = load_scene(d, cache_dir=tmp_path / "cache")
    assert s.has_masks and np.array_equal(s.load_mask(2), truth[2])


def test_partly_masked_captures_are_a_clear_error(tmp_path):
    d = write_turntable_scene(tmp_path / "c", N, W, H, fmt="colmap", n_points=200)
    (d / "masks" / "frame_00003.png").unlink()
    with pytest.raises(MaskError, match=r"1 of 6 images have no mask in masks/.*frame_00003"):
        load_scene(d, cache_dir=tmp_path / "cache")
    assert not load_scene(d, cache_dir=tmp_path / "c2", cfg=IngestConfig(masks="ignore")).has_masks

    d = write_turntable_scene(tmp_path / "n", N, W, H, fmt="nerfstudio")
    meta = json.loads((d / "transforms.json").read_text())
    meta["frames"][2].pop("mask_path")
    (d / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(MaskError, match=r"1 of 6 frames have no mask_path.*frame_00002") as e:
        load_scene(d, cache_dir=tmp_path / "cache")
    assert "scene 'n'" in str(e.value) and "transforms.json" in str(e.value)


def test_wrong_size_and_corrupt_masks_name_the_file(tmp_path):
    import cv2

    for fmt in ("colmap", "nerfstudio"):
        d = write_turntable_scene(tmp_path / fmt, N, W, H, fmt=fmt, n_points=200)
        bad = d / "masks" / "frame_00004.png"
        cv2.imwrite(str(bad), np.zeros((H // 2, W // 2), np.uint8))
        with pytest.raises(MaskError, match=r"mask is 16x12 but its image 'frame_00004.png' "
                           r"is 32x24") as e:
            load_scene(d, cache_dir=tmp_path / "cache")
        assert str(bad) in str(e.value) and f"scene '{fmt}'" in str(e.value)
        bad.write_bytes(b"not a png")
        with pytest.raises(CorruptImageError, match="mask cannot be decoded") as e:
            load_scene(d, cache_dir=tmp_path / "cache")
        assert str(bad) in str(e.value)


def test_masks_are_undistorted_and_resized_like_their_images(tmp_path):
    """The image *is* its mask (grey 0/255): after undistortion (pycolmap, bilinear) and a
    resize (area), thresholding the image must give the warped mask almost everywhere."""
    import cv2

    d = write_turntable_scene(tmp_path / "ud", N, 64, 48, fmt="nerfstudio")
    for p in sorted((d / "masks").glob("*.png")):
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(d / "images" / p.name), np.repeat(m[..., None], 3, -1))
    meta = json.loads((d / "transforms.json").read_text())
    meta.update(k1=-0.15, k2=0.02)  # OPENCV with distortion
    (d / "transforms.json").write_text(json.dumps(meta))
    for cfg in (IngestConfig(), IngestConfig(max_image_size=40)):
        s = load_scene(d, cache_dir=tmp_path / f"cache{cfg.max_image_size}", cfg=cfg)
        assert s.undistorted and s.has_masks
        agree = []
        for i in range(N):
            m, img = s.load_mask(i), s.load_image(i)
            assert m.shape == img.shape[:2] == (int(s.cameras.height[i]), int(s.cameras.width[i]))
            agree.append(np.mean(m == (img[..., 0] >= 128)))
        # exact mapping: >= 0.999 measured at 96x72; a half-pixel shift gives ~0.99
        assert min(agree) > (0.995 if cfg.max_image_size is None else 0.97), agree
        if cfg.max_image_size:
            assert max(s.cameras.width.max(), s.cameras.height.max()) <= 40
    # a pinhole capture only resized (no undistortion): nearest resize, still binary
    d2 = tmp_path / "rs"
    shutil.copytree(d, d2)
    meta.update(k1=0.0, k2=0.0)
    (d2 / "transforms.json").write_text(json.dumps(meta))
    s = load_scene(d2, cache_dir=tmp_path / "c_rs", cfg=IngestConfig(max_image_size=32))
    assert not s.undistorted and s.has_masks
    m, img = s.load_mask(0), s.load_image(0)
    assert m.shape == img.shape[:2] == (24, 32)
    assert np.mean(m == (img[..., 0] >= 128)) > 0.95
