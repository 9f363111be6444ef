"""FreeViewSet: what publish writes is what the reader returns (write -> read round trip)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from freescale_core.errors import StoreError
from freescale_core.store.reader import FreeViewSet, open_scenes
from freescale_core.store.store import Store


def _scene_pkl(store, sid):
    with open(Store(store).work_dir(sid) / "scene.pkl", "rb") as f:
        return pickle.load(f)


def _fv_pkl(store, sid):
    with open(Store(store).work_dir(sid) / "freeviews.pkl", "rb") as f:
        return pickle.load(f)


def test_training_views_round_trip(dataset_store):
    for fvs in open_scenes(dataset_store):
        scene = _scene_pkl(dataset_store, fvs.scene_id)
        ids, cams = fvs.cameras("train")
        assert len(ids) == len(scene)
        np.testing.assert_array_equal(cams.world_from_cam, scene.cameras.world_from_cam)
        for k in ("fx", "fy", "cx", "cy", "width", "height"):
            np.testing.assert_array_equal(getattr(cams, k), getattr(scene.cameras, k))
        # the published images are the (undistorted) pinhole images the Scene was built from
        for i in (0, len(scene) // 2, len(scene) - 1):
            np.testing.assert_array_equal(fvs.rgb(int(ids[i])), scene.load_image(i))
            assert fvs.image_path(int(ids[i])).stat().st_size == \
                scene.image_paths[i].stat().st_size
        xyz, rgb = fvs.points()
        np.testing.assert_array_equal(xyz, scene.points_xyz)
        np.testing.assert_array_equal(rgb, scene.points_rgb)
        v = fvs.dataset_views()
        np.testing.assert_array_equal(v.capture_index[~v.is_free],
                                      np.argsort(scene.capture_order))


def test_free_views_round_trip_at_their_true_size(dataset_store):
    for fvs in open_scenes(dataset_store):
        fv = _fv_pkl(dataset_store, fvs.scene_id)
        ids, cams = fvs.cameras("free")
        assert len(ids) == fv.n_final > 0
        T = int((~fvs.dataset_views().is_free).sum())
        np.testing.assert_array_equal(ids, T + np.asarray(fv.final_candidates))
        for k, vid in enumerate(ids):
            rgb, dep = fvs.rgb(int(vid)), fvs.depth(int(vid))
            assert rgb.shape == (cams.height[k], cams.width[k], 3)
            np.testing.assert_array_equal(rgb, fv.rgb[k])
            np.testing.assert_array_equal(dep, fv.depth[k])
        v = fvs.dataset_views()
        assert set(v.mode[v.is_free]) <= {"orbit", "spiral", "lemniscate", "interpolation",
                                          "move_up", "move_down", "move_left", "move_right",
                                          "dolly_in", "dolly_out"}
        assert np.isfinite(v.brisque[v.is_free]).all() and (v.capture_index[v.is_free] == -1).all()


def test_kermit_free_views_differ_in_size_and_are_cropped(dataset_store):
    if "kermit" not in Store(dataset_store).scene_ids():
        pytest.skip("kermit not in the shared datasets")
    fvs = FreeViewSet.open(dataset_store, "kermit")
    ids, cams = fvs.cameras("free")
    sizes = {(int(h), int(w)) for h, w in zip(cams.height, cams.width)}
    assert len(sizes) > 1  # the padded zarr array holds views of different sizes
    assert {fvs.rgb(int(v)).shape[:2] for v in ids} == sizes


def test_graph_config_and_pickling(dataset_store):
    fvs = FreeViewSet.open(dataset_store, "sample_a")
    src, dst, w = fvs.graph()
    ids = set(fvs.dataset_views().view_id.tolist())
    assert len(src) and set(src) <= ids and set(dst) <= ids and (src < dst).all()
    assert ((w >= 0) & (w <= 1)).all()
    assert len(fvs.graph(dataset_only=False)[0]) >= len(src)
    cfg = fvs.config()
    row = next(r for r in Store(dataset_store).manifest().to_pylist() if r["scene_id"] == "sample_a")
    assert cfg["config_hash"] == row["config_hash"] and cfg["config"]["preset"] == "fast"
    clone = pickle.loads(pickle.dumps(fvs))
    np.testing.assert_array_equal(clone.rgb(int(fvs.cameras("free")[0][0])),
                                  fvs.rgb(int(fvs.cameras("free")[0][0])))
    assert FreeViewSet.from_version_dir(fvs.version_dir).scene_id == "sample_a"


def test_reader_errors_name_scene(dataset_store, tmp_path):
    with pytest.raises(StoreError, match="nope"):
        FreeViewSet.open(dataset_store, "nope")
    with pytest.raises(StoreError, match="not a published version"):
        FreeViewSet(tmp_path)
    fvs = FreeViewSet.open(dataset_store, "sample_a")
    with pytest.raises(KeyError, match="sample_a"):
        fvs.rgb(10 ** 6)
    with pytest.raises(KeyError, match="training view"):
        fvs.depth(0)
    with pytest.raises(StoreError, match="not in the store"):
        open_scenes(dataset_store, ["nope"])


@settings(max_examples=60, deadline=None)
@given(h=st.integers(9, 120), w=st.integers(9, 120), R=st.integers(8, 64),
       u=st.floats(0.01, 0.99), v=st.floats(0.01, 0.99))
def test_resize_crop_moves_intrinsics_with_the_pixels(h, w, R, u, v):
    """A point at continuous pixel (u w, v h) lands where the new intrinsics project it."""
    from freescale_core.store.shards import resize_crop

    img = np.zeros((h, w, 3), np.uint8)
    K = np.array([50.0, 60.0, w / 2, h / 2])
    out, K2 = resize_crop(img, K, R)
    assert out.shape == (R, R, 3)
    x, y = (u * w - K[2]) / K[0], (v * h - K[3]) / K[1]  # normalised camera coordinates
    s = R / min(h, w)
    nw = R if w <= h else max(R, int(round(w * s)))
    nh = R if h < w else max(R, int(round(h * s)))
    if w == h:
        nw = nh = R
    x0, y0 = (nw - R) // 2, (nh - R) // 2
    np.testing.assert_allclose(K2[0] * x + K2[2], u * w * nw / w - x0, atol=1e-9)
    np.testing.assert_allclose(K2[1] * y + K2[3], v * h * nh / h - y0, atol=1e-9)


def test_resize_crop_of_a_marked_pixel():
    """Golden: a bright pixel block stays where the intrinsics say after resize + crop."""
    from freescale_core.store.shards import resize_crop

    img = np.zeros((100, 200, 3), np.uint8)
    img[40:60, 110:130] = 255  # centre (120, 50) in continuous pixels
    out, K2 = resize_crop(img, np.array([100.0, 100.0, 100.0, 50.0]), 50)
    np.testing.assert_allclose(K2, [50.0, 50.0, 25.0, 25.0])  # 200x100 -> 100x50, crop x0=25
    # x = (120 - 100) / 100 = 0.2 -> u = K2.fx * 0.2 + K2.cx = 35
    u, v = K2[0] * 0.2 + K2[2], K2[1] * 0.0 + K2[3]
    ys, xs = np.nonzero(out[..., 0] > 127)
    assert abs(xs.mean() + 0.5 - u) < 0.6 and abs(ys.mean() + 0.5 - v) < 0.6
