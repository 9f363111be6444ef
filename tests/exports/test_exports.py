"""Exports, read back by real clients: our own ingest (nerfstudio, COLMAP), pycolmap,
plyfile, torch (gsplat checkpoint), and LVSM's metadata conventions."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from freescale_core.errors import StoreError
from freescale_core.exports import export
from freescale_core.exports.common import frame_order
from freescale_core.geometry.cameras import invert_pose
from freescale_core.store.reader import open_scenes

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def exports(dataset_store, tmp_path_factory):
    root = tmp_path_factory.mktemp("exports")
    out = {}
    for fmt in ("nerfstudio", "colmap", "lvsm", "gsplat"):
        out[fmt] = export(fmt, dataset_store, root / fmt).out
    out["nerfstudio_val"] = export("nerfstudio", dataset_store, root / "ns_val",
                                   free_views="val", depth=True).out
    return out


def _expected(fvs):
    """The reader's cameras in the exports' frame order (captured in capture order, free)."""
    o = frame_order(fvs)
    return fvs.dataset_views().cameras.subset(o), fvs.dataset_views().is_free[o]


def _same_cameras(a, b, tol=1e-6):
    np.testing.assert_allclose(a.world_from_cam, b.world_from_cam, atol=tol, rtol=0)
    for k in ("fx", "fy", "cx", "cy"):
        np.testing.assert_allclose(getattr(a, k), getattr(b, k), atol=tol, rtol=0)
    for k in ("width", "height"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))


@pytest.mark.parametrize("fmt", ["nerfstudio", "nerfstudio_val", "colmap"])
def test_our_ingest_reads_the_export_back(dataset_store, exports, fmt, tmp_path):
    from freescale_core.scene.io import load_scene

    for fvs in open_scenes(dataset_store):
        scene = load_scene(exports[fmt] / fvs.scene_id, scene_id=fvs.scene_id,
                           cache_dir=tmp_path)
        cams, is_free = _expected(fvs)
        assert not scene.undistorted and len(scene) == len(cams)
        _same_cameras(scene.cameras, cams)
        from scipy.spatial import cKDTree

        xyz, _ = fvs.points()  # same set (COLMAP may reorder; the PLY is float32)
        assert len(scene.points_xyz) == len(xyz)
        dist, _ = cKDTree(xyz).query(scene.points_xyz)
        assert dist.max() < 1e-6 * np.abs(xyz).max() + 1e-7
        k = int(np.flatnonzero(is_free)[0])  # the first free view's pixels survive
        vid = int(fvs.dataset_views().view_id[frame_order(fvs)[k]])
        np.testing.assert_array_equal(scene.load_image(k), fvs.rgb(vid))


def test_nerfstudio_transforms_json(dataset_store, exports):
    for fvs in open_scenes(dataset_store):
        cams, is_free = _expected(fvs)
        meta = json.loads((exports["nerfstudio"] / fvs.scene_id / "transforms.json").read_text())
        fr = meta["frames"]
        assert [f["freescale"]["is_free"] for f in fr] == is_free.tolist()
        # OpenGL camera-to-world: camera looks down -z, so -z column = our +z column
        tm = np.array([f["transform_matrix"] for f in fr])
        np.testing.assert_allclose(-tm[:, :3, 2], cams.world_from_cam[:, :3, 2], atol=1e-9)
        free = [f["file_path"] for f in fr if f["freescale"]["is_free"]]
        assert set(free) <= set(meta["train_filenames"])
        val = json.loads((exports["nerfstudio_val"] / fvs.scene_id / "transforms.json").read_text())
        assert set(val["val_filenames"]) == set(free)
        assert not set(free) & set(val["train_filenames"])


def test_nerfstudio_depth_pngs_hold_the_depth(dataset_store, exports):
    import cv2

    for fvs in open_scenes(dataset_store):
        d = exports["nerfstudio_val"] / fvs.scene_id
        meta = json.loads((d / "transforms.json").read_text())
        s = meta["depth_unit_scale_factor"]
        for f in meta["frames"]:
            png = cv2.imread(str(d / f["depth_file_path"]), cv2.IMREAD_UNCHANGED)
            assert png.dtype == np.uint16 and png.shape == (f["h"], f["w"])
            if f["freescale"]["is_free"]:
                true = fvs.depth(f["freescale"]["view_id"])
                np.testing.assert_allclose(png * s, true, atol=0.51 * s)
            else:
                assert not png.any()


def test_colmap_export_reads_in_pycolmap(dataset_store, exports):
    import pycolmap

    for fvs in open_scenes(dataset_store):
        rec = pycolmap.Reconstruction(str(exports["colmap"] / fvs.scene_id / "sparse" / "0"))
        cams, _ = _expected(fvs)
        assert rec.num_images() == len(cams) and rec.num_points3D() == len(fvs.points()[0])
        for iid, im in rec.images.items():
            k = int(im.name.split("_")[0])
            c = rec.cameras[im.camera_id]
            assert c.model.name == "PINHOLE" and c.width == cams.width[k]
            np.testing.assert_allclose(c.params, [cams.fx[k], cams.fy[k], cams.cx[k], cams.cy[k]])
            np.testing.assert_allclose(im.cam_from_world().matrix(),
                                       invert_pose(cams.world_from_cam[k])[:3], atol=1e-9)


def test_lvsm_layout(dataset_store, exports):
    from PIL import Image

    out = exports["lvsm"]
    lines = (out / "full_list.txt").read_text().split()
    index = json.loads((out / "evaluation_index.json").read_text())
    for fvs in open_scenes(dataset_store):
        mp = out / "metadata" / f"{fvs.scene_id}.json"
        assert str(mp) in lines
        meta = json.loads(mp.read_text())
        assert meta["scene_name"] == fvs.scene_id
        cams, is_free = _expected(fvs)
        fr = meta["frames"]
        # captured views first, in capture order (LVSM's frame-distance sampler)
        cap = [f["freescale"]["capture_index"] for f in fr if not f["freescale"]["is_free"]]
        assert cap == sorted(cap) and [f["freescale"]["is_free"] for f in fr] == is_free.tolist()
        for k, f in enumerate(fr):
            assert Path(f["image_path"]).name == f"{k:05d}.png"
            w, h = Image.open(f["image_path"]).size
            assert (w, h) == (cams.width[k], cams.height[k])
            np.testing.assert_allclose(np.linalg.inv(np.array(f["w2c"])),
                                       cams.world_from_cam[k], atol=1e-9)
            np.testing.assert_allclose(f["fxfycxcy"], [cams.fx[k], cams.fy[k], cams.cx[k],
                                                       cams.cy[k]])
        ix = index[fvs.scene_id]
        assert len(ix["context"]) == 2 and len(ix["target"]) == 3
        assert not set(ix["context"]) & set(ix["target"])
        assert all(0 <= i < len(fr) for i in ix["context"] + ix["target"])
        assert all(not fr[i]["freescale"]["is_free"] for i in ix["context"])


def test_gsplat_checkpoint_ply_and_cameras(dataset_store, exports):
    import plyfile
    import torch

    from freescale_core.scene.ply import read_ply

    for fvs in open_scenes(dataset_store):
        d = exports["gsplat"] / fvs.scene_id
        ck = torch.load(d / "ckpt.pt", weights_only=True)
        sp = ck["splats"]
        g = read_ply(fvs.gaussians_ply)
        N, K = len(g), g.sh.shape[1]
        assert ck["step"] == 0
        assert {k: tuple(v.shape) for k, v in sp.items()} == {
            "means": (N, 3), "scales": (N, 3), "quats": (N, 4), "opacities": (N,),
            "sh0": (N, 1, 3), "shN": (N, K - 1, 3)}
        assert all(v.dtype == torch.float32 for v in sp.values())
        ply = plyfile.PlyData.read(str(d / "gaussians.ply"))
        v = ply["vertex"]
        np.testing.assert_array_equal(np.asarray(v["x"]), sp["means"][:, 0].numpy())
        np.testing.assert_array_equal(np.asarray(v["opacity"]), sp["opacities"].numpy())
        np.testing.assert_array_equal(np.asarray(v["rot_0"]), sp["quats"][:, 0].numpy())
        np.testing.assert_array_equal(np.asarray(v["scale_2"]), sp["scales"][:, 2].numpy())
        c = np.load(d / "cameras.npz")
        cams, is_free = _expected(fvs)
        np.testing.assert_allclose(c["viewmats"], invert_pose(cams.world_from_cam), atol=1e-5)
        np.testing.assert_allclose(c["Ks"], cams.K, rtol=1e-6)
        np.testing.assert_array_equal(c["is_free"], is_free)
        assert all((d / n).is_file() for n in c["image_names"])


def test_export_is_atomic(dataset_store, tmp_path, monkeypatch):
    import freescale_core.exports.lvsm as L

    out = tmp_path / "x"
    calls = {"n": 0}
    orig = L.write_png

    def flaky(path, rgb):
        calls["n"] += 1
        if calls["n"] == 5:
            raise OSError("disk full")
        orig(path, rgb)

    monkeypatch.setattr(L, "write_png", flaky)
    with pytest.raises(OSError):
        export("lvsm", dataset_store, out)
    assert not out.exists() and not list(tmp_path.iterdir())  # nothing half-written
    monkeypatch.setattr(L, "write_png", orig)
    export("lvsm", dataset_store, out)
    with pytest.raises(StoreError, match="--overwrite"):
        export("lvsm", dataset_store, out)
    before = (out / "full_list.txt").stat().st_ino
    export("lvsm", dataset_store, out, overwrite=True)
    assert (out / "full_list.txt").stat().st_ino != before
    assert [p.name for p in tmp_path.iterdir()] == ["x"]


def test_cli_export_prints_files_and_load_command(dataset_store, tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.run([sys.executable, "-m", "flows.cli", "export", "colmap",
                        str(dataset_store), str(tmp_path / "c"), "--scenes", "sample_a"],
                       cwd=REPO, env=env, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "sample_a/sparse/0/images.txt" in p.stdout and "pycolmap.Reconstruction" in p.stdout
    p = subprocess.run([sys.executable, "-m", "flows.cli", "export", "colmap",
                        str(dataset_store), str(tmp_path / "c2"), "--scenes", "nope"],
                       cwd=REPO, env=env, capture_output=True, text=True)
    assert p.returncode == 2 and "nope" in p.stderr
