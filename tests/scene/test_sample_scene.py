"""The embedded sample scene and its ground-truth oracle (freescale_core.scene.sample).

Reference tests (pinhole ray caster vs per-ray world caster, bilinear taps vs texels),
property tests (crop invariance of the renderer, box faces), and format tests (pycolmap
parses the COLMAP model, poses/tracks/depth agree with the oracle, determinism, atomicity).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.scene import sample as ss
from freescale_core.geometry.cameras import Cameras, invert_pose, look_at
from freescale_core.errors import MissingInputError, SceneError
from freescale_core.geometry.raycast import TextureBank, box_faces, cast_pinhole, cast_rays
from freescale_core.scene.sample import SampleWorld, SceneSpec, write_sample_scene
from freescale_core.scene.scene import read_rgb

SMALL = dict(n_views=8, width=96, height=72, seed=3, n_points=300)


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory) -> Path:
    return write_sample_scene(tmp_path_factory.mktemp("small") / "scene", **SMALL)


@pytest.fixture(scope="module")
def small_world(small_scene) -> SampleWorld:
    return SampleWorld.load(small_scene)


def _cam_from_world(image: pycolmap.Image) -> np.ndarray:
    pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(pose.matrix())


def _tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------- files + COLMAP
def test_layout_on_disk(small_scene):
    names = sorted(p.name for p in (small_scene / "images").iterdir())
    assert names == [f"frame_{i:05d}.png" for i in range(SMALL["n_views"])]
    for f in ("cameras.txt", "images.txt", "points3D.txt"):
        assert (small_scene / "sparse" / "0" / f).is_file()
    assert (small_scene / "scene.json").is_file()
    img = read_rgb(small_scene / "images" / names[0])
    assert img.shape == (SMALL["height"], SMALL["width"], 3)
    leftovers = [p.name for p in small_scene.parent.iterdir() if p.name.startswith(".")]
    assert leftovers == []


def test_pycolmap_parses_and_poses_round_trip(small_scene, small_world):
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    cams = small_world.cameras
    assert rec.num_images() == len(cams) == SMALL["n_views"]
    assert rec.num_points3D() == small_world.spec.n_points > 50
    cam = rec.camera(1)
    assert cam.model_name == "PINHOLE"
    assert (cam.width, cam.height) == (SMALL["width"], SMALL["height"])
    np.testing.assert_array_equal(np.asarray(cam.params),
                                  [cams.fx[0], cams.fy[0], cams.cx[0], cams.cy[0]])
    for i in range(len(cams)):
        image = rec.image(i + 1)
        assert image.name == small_world.image_names[i] == f"frame_{i:05d}.png"
        expected = invert_pose(cams.world_from_cam[i])[:3]
        np.testing.assert_allclose(_cam_from_world(image), expected, atol=1e-9, rtol=0)


def test_tracks_consistent_and_reproject(small_scene, small_world):
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    cams = small_world.cameras
    max_err, n_obs = 0.0, 0
    for pid, point in rec.points3D.items():
        elements = point.track.elements
        assert len(elements) >= 2
        uv, z = cams.project(np.asarray(point.xyz)[None])
        for el in elements:
            p2d = rec.image(el.image_id).points2D[el.point2D_idx]
            assert p2d.point3D_id == pid
            i = el.image_id - 1
            assert z[i, 0] > 0
            max_err = max(max_err, float(np.abs(uv[i, 0] - np.asarray(p2d.xy)).max()))
            n_obs += 1
    assert n_obs == sum(len(p.track.elements) for p in rec.points3D.values())
    # every listed 2D point belongs to a track
    for image in rec.images.values():
        assert all(rec.exists_point3D(p.point3D_id) for p in image.points2D)
    assert max_err < 0.5
    assert max_err < 1e-6  # observations are exact projections


def test_sparse_points_are_visible_surface_points(small_scene, small_world):
    """Each observation: the oracle's depth through exactly that point equals its camera z."""
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    cams = small_world.cameras
    rng = np.random.default_rng(0)
    pids = rng.choice(list(rec.points3D.keys()), size=40, replace=False)
    for pid in pids:
        point = rec.points3D[int(pid)]
        xyz = np.asarray(point.xyz)
        for el in list(point.track.elements)[:3]:
            i = el.image_id - 1
            u, v = np.asarray(rec.image(el.image_id).points2D[el.point2D_idx].xy)
            z = (invert_pose(cams.world_from_cam[i]) @ np.append(xyz, 1.0))[2]
            # a 1x1 camera whose only pixel centre (0.5, 0.5) is the observation (u, v)
            _, depth = small_world.render(cams.world_from_cam[i], cams.fx[i], cams.fy[i],
                                          cams.cx[i] - (u - 0.5), cams.cy[i] - (v - 0.5), 1, 1)
            assert depth[0, 0] == pytest.approx(z, rel=1e-5)


def test_depth_map_consistent_with_sparse_points(small_scene, small_world):
    """Full-size depth maps at the observed pixels match the points' camera z."""
    rec = pycolmap.Reconstruction(str(small_scene / "sparse" / "0"))
    cams = small_world.cameras
    rel, col_err = [], []
    for i in range(len(cams)):
        rgb, depth = small_world.render_camera(cams, i)
        image = rec.image(i + 1)
        T = invert_pose(cams.world_from_cam[i])
        for p2d in image.points2D:
            point = rec.points3D[p2d.point3D_id]
            x, y = np.floor(np.asarray(p2d.xy)).astype(int)
            z = (T @ np.append(point.xyz, 1.0))[2]
            rel.append(abs(depth[y, x] - z) / z)
            col_err.append(np.abs(rgb[y, x].astype(int) - np.asarray(point.color, int)).mean())
    rel = np.asarray(rel)
    assert np.median(rel) < 0.01
    assert np.mean(rel < 0.05) > 0.9  # the rest sit on depth edges
    assert np.median(col_err) < 30  # point colour = surface colour (unfiltered texel)


def test_depth_is_zero_only_for_sky(small_world):
    cams = small_world.cameras
    # look straight up from above the scene: nothing but sky
    T = look_at(np.array([0.0, 0.0, 5.0]), np.array([0.0, 0.01, 10.0]), np.array([0, 1.0, 0]))
    rgb, depth = small_world.render(T, cams.fx[0], cams.fy[0], cams.cx[0], cams.cy[0],
                                    int(cams.width[0]), int(cams.height[0]))
    assert np.all(depth == 0.0)
    assert rgb.std(axis=(0, 1)).max() < 20  # smooth gradient
    _, depth = small_world.render_camera(cams, 0)
    assert np.all(np.isfinite(depth)) and depth.dtype == np.float32
    assert (depth > 0).mean() > 0.8


# --------------------------------------------------------------------------- the oracle
def test_oracle_reproduces_training_images_exactly(small_scene, small_world):
    cams = small_world.cameras
    for i in range(len(cams)):
        rgb, _ = small_world.render_camera(cams, i)
        png = read_rgb(small_scene / "images" / small_world.image_names[i])
        np.testing.assert_array_equal(rgb, png)


def test_oracle_renders_other_intrinsics(small_world):
    """Half-resolution render of a training pose ~ downsampled full render."""
    cams = small_world.cameras
    rgb, depth = small_world.render_camera(cams, 2)
    half = cams.scaled(0.5)
    rgb2, depth2 = small_world.render_camera(half, 2)
    assert rgb2.shape == (36, 48, 3)
    down = rgb.reshape(36, 2, 48, 2, 3).astype(float).mean(axis=(1, 3))
    assert np.abs(down - rgb2).mean() < 12


def test_pinhole_caster_matches_per_ray_reference(small_world):
    """Fast camera-frame caster with bounding-box culling vs obvious world-frame rays."""
    cams = small_world.cameras
    T = cams.world_from_cam[1]
    W, H = 40, 30
    fx, fy, cx, cy = 35.0, 36.0, 20.3, 14.8
    hits = cast_pinhole(small_world.quads, T, fx, fy, cx, cy, W, H, 0.01)
    xs, ys = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_cam = np.stack([(xs - cx) / fx, (ys - cy) / fy, np.ones_like(xs)], -1).reshape(-1, 3)
    ref = cast_rays(small_world.quads, T[:3, 3], d_cam @ T[:3, :3].T, 0.01)
    same = ref.quad == hits.quad.ravel()
    assert same.mean() > 0.99  # ties on shared box edges may go either way
    np.testing.assert_allclose(hits.t.ravel()[same], ref.t[same], rtol=1e-9)


@settings(max_examples=8, deadline=None)
@given(x0=st.integers(0, 60), y0=st.integers(0, 40), w=st.integers(1, 36),
       h=st.integers(1, 32), view=st.integers(0, SMALL["n_views"] - 1))
def test_crop_render_equals_crop_of_render(small_world, x0, y0, w, h, view):
    """Rendering a window (shifted principal point) gives the same pixels as cropping."""
    cams = small_world.cameras
    W, H = int(cams.width[0]), int(cams.height[0])
    w, h = min(w, W - x0), min(h, H - y0)
    rgb, depth = small_world.render_camera(cams, view)
    rgb_c, depth_c = small_world.render(cams.world_from_cam[view], cams.fx[view],
                                        cams.fy[view], cams.cx[view] - x0, cams.cy[view] - y0,
                                        w, h)
    np.testing.assert_allclose(depth_c, depth[y0:y0 + h, x0:x0 + w], rtol=1e-5)
    diff = np.abs(rgb_c.astype(int) - rgb[y0:y0 + h, x0:x0 + w])
    assert diff.max() <= 2 and (diff > 0).mean() < 0.02


def test_texture_bank_taps_and_modes():
    rng = np.random.default_rng(1)
    tex = rng.random((2, 8, 8, 3)).astype(np.float32)
    bank = TextureBank(tex)
    assert bank.n_levels == 4
    iy, ix = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    iy, ix = iy.ravel(), ix.ravel()
    u, v = (ix + 0.5) / 8, (iy + 0.5) / 8
    for t in (0, 1):
        for wrap in (False, True):
            got = bank.sample(np.full(64, t), u, v, np.zeros(64), np.full(64, wrap))
            np.testing.assert_allclose(got, tex[t, iy, ix], atol=1e-6)
    # between the last and first column: repeat blends them, clamp does not
    u_edge, v_mid = np.array([1.0]), np.array([0.5 / 8])
    wrapped = bank.sample(np.zeros(1), u_edge, v_mid, np.zeros(1), np.ones(1, bool))
    clamped = bank.sample(np.zeros(1), u_edge, v_mid, np.zeros(1), np.zeros(1, bool))
    np.testing.assert_allclose(wrapped[0], 0.5 * (tex[0, 0, 7] + tex[0, 0, 0]), atol=1e-6)
    np.testing.assert_allclose(clamped[0], tex[0, 0, 7], atol=1e-6)
    # the coarsest level is the mean colour
    top = bank.sample(np.zeros(1), np.array([0.3]), np.array([0.6]), np.array([3.0]),
                      np.ones(1, bool))
    np.testing.assert_allclose(top[0], tex[0].reshape(-1, 3).mean(0), atol=1e-5)


@settings(max_examples=20, deadline=None)
@given(yaw=st.floats(-180, 180), hx=st.floats(0.05, 2), hy=st.floats(0.05, 2),
       hz=st.floats(0.05, 2))
def test_box_faces_are_outward_and_right_handed(yaw, hx, hy, hz):
    c = np.array([0.3, -0.2, 1.0])
    centers, rights, ups, halves = box_faces(c, np.array([hx, hy, hz]), yaw)
    normals = np.cross(rights, ups)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    assert np.all(np.einsum("ij,ij->i", normals, centers - c) > 0)
    np.testing.assert_allclose(np.einsum("ij,ij->i", rights, ups), 0.0, atol=1e-12)
    assert np.allclose(ups[:4, 2], 1.0)  # side faces: texture upright


# --------------------------------------------------------------------------- the capture
def test_capture_path_is_upright_smooth_and_looks_at_scene():
    cams = ss.capture_path(40, 128, 96, seed=5)
    up = np.array([0.0, 0.0, 1.0])
    assert np.all(cams.world_from_cam[:, :3, 1] @ up < -0.8)  # image down = world down
    R = cams.world_from_cam[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3),
                               R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    steps = np.linalg.norm(np.diff(cams.centers, axis=0), axis=1)
    assert steps.max() < 3 * np.median(steps)  # video-like: no jumps
    uv, z = cams.project(np.array([[0.0, 0.35, 0.35]]))
    assert np.all(z > 0)
    assert np.all((uv[:, 0, 0] > 0.2 * 128) & (uv[:, 0, 0] < 0.8 * 128))
    assert np.all((uv[:, 0, 1] > 0.2 * 96) & (uv[:, 0, 1] < 0.8 * 96))


# --------------------------------------------------------------------------- determinism etc.
def test_same_seed_byte_identical_other_seed_differs(small_scene, tmp_path):
    again = write_sample_scene(tmp_path / "again", **SMALL)
    assert _tree_digest(again) == _tree_digest(small_scene)
    other = write_sample_scene(tmp_path / "other", **{**SMALL, "seed": 4})
    a, b = _tree_digest(other), _tree_digest(small_scene)
    assert a.keys() == b.keys()
    assert a["scene.json"] != b["scene.json"]
    assert a["images/frame_00000.png"] != b["images/frame_00000.png"]


def test_scene_json_round_trip(small_scene, small_world):
    raw = (small_scene / "scene.json").read_text()
    spec = SceneSpec.model_validate_json(raw)
    assert spec == small_world.spec
    assert json.loads(raw) == spec.model_dump(mode="json")
    assert spec.format == "freescale-sample-scene" and spec.version == ss.SCENE_VERSION
    assert spec.units == "metres"
    world = SampleWorld.from_spec(spec)
    np.testing.assert_array_equal(world.quads.center, small_world.quads.center)
    np.testing.assert_array_equal(world.cameras.world_from_cam,
                                  small_world.cameras.world_from_cam)
    assert len(spec.boxes) == 5 and len(world.quads) == len(spec.quads) + 6 * len(spec.boxes)


def test_load_errors_name_scene_and_file(tmp_path):
    with pytest.raises(MissingInputError) as e:
        SampleWorld.load(tmp_path / "nope")
    assert "nope" in str(e.value)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "scene.json").write_text('{"format": "freescale-sample-scene", "seed": "x"}')
    with pytest.raises(SceneError) as e:
        SampleWorld.load(bad)
    assert "bad" in str(e.value) and "scene.json" in str(e.value)


def test_atomic_replace_and_failure_keeps_old_scene(small_scene, tmp_path, monkeypatch):
    target = write_sample_scene(tmp_path / "s", **{**SMALL, "n_views": 3, "n_points": 20})
    before = _tree_digest(target)

    def boom(*args, **kwargs):
        raise RuntimeError("simulated crash")

    monkeypatch.setattr(ss, "sparse_points", boom)
    with pytest.raises(RuntimeError):
        write_sample_scene(target, **SMALL)
    assert _tree_digest(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]
    monkeypatch.undo()
    write_sample_scene(target, **SMALL)
    assert _tree_digest(target) == _tree_digest(small_scene)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]


def test_default_scene(tmp_path):
    """The default scene (make run's input): 36 views, 256x192, thousands of points."""
    scene = write_sample_scene(tmp_path / "default")
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    assert rec.num_images() == 36
    assert 1000 <= rec.num_points3D() <= 3000
    world = SampleWorld.load(scene)
    cams = world.cameras
    assert isinstance(cams, Cameras) and len(cams) == 36
    assert (int(cams.width[0]), int(cams.height[0])) == (256, 192)
    for i in (0, 35):
        rgb, depth = world.render_camera(cams, i)
        np.testing.assert_array_equal(rgb, read_rgb(scene / "images" / f"frame_{i:05d}.png"))
        assert 1.0 < np.median(depth[depth > 0]) < 10.0  # metres
    xyz, normal, rgb = world.sample_surface(500, np.random.default_rng(0))
    assert xyz.shape == (500, 3) and rgb.dtype == np.uint8
    assert np.all(xyz[:, 2] > -1e-9) and np.all(xyz[:, 2] < 2.21)


def test_banded_render_is_bit_identical(small_world, monkeypatch):
    """Large images are rendered in row bands; bands must not change a single bit."""
    cams = small_world.cameras
    full = small_world.render_camera(cams, 4)
    monkeypatch.setattr(ss, "RENDER_BAND_SAMPLES", 7 * 96 * 4)  # 7-row bands, last one short
    banded = small_world.render_camera(cams, 4)
    np.testing.assert_array_equal(banded[0], full[0])
    np.testing.assert_array_equal(banded[1], full[1])


def test_scene_subset_and_views_for_keep_capture_order(tmp_path):
    from freescale_core.scene.io import load_scene

    d = ss.write_sample_scene(tmp_path / "s", n_views=12, width=48, height=36)
    scene = load_scene(d, cache_dir=tmp_path / "c")
    gen, held = scene.views_for("ood")
    train_idx, test_idx = scene.split("ood")
    assert len(gen) == len(train_idx) and len(held) == len(test_idx)
    assert sorted(gen.image_names) == sorted(scene.image_names[i] for i in train_idx)
    # capture order of the subset = the parent's order restricted to it
    assert [gen.image_names[i] for i in gen.capture_order] == \
        [scene.image_names[i] for i in train_idx]
    np.testing.assert_array_equal(gen.cameras.world_from_cam,
                                  scene.cameras.world_from_cam[np.sort(train_idx)])
    same, none = scene.views_for("all")
    assert same is scene and none is None
