"""Pose rectification (stage 8), reference selection and image rectification (stage 10).

The image tests use a small exact world: a tilted, textured plane ray-cast in closed form
(``PlaneWorld``), so the true image at any pose is known. ``test_freeviews.py`` reuses it.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import skimage.data
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.geometry.cameras import (look_at, make_pose, quat_wxyz_to_rotmat,
                                    rotation_angle_deg)
from freescale_core.freeviews.rectify_image import (NoneRectifier, RectifierUnavailable,
                                          RenderedView, ReprojectRectifier, angle_weight,
                                          make_rectifier, register_rectifier,
                                          triangulation_angle_deg, RECTIFIERS)
from freescale_core.freeviews.rectify_pose import (interpolate_pose, nearest_training_camera,
                                         rectification_poses)
from freescale_core.freeviews.references import (ViewGraph, graph_reference, pose_distances,
                                       select_reference)
from schemas.freeview import PoseRectifyConfig, RectifierConfig, ReferenceConfig

UP = np.array([0.0, -1.0, 0.0])  # world "up" is -y (OpenCV-like world)


# --------------------------------------------------------------------------- synthetic world
class PlaneWorld:
    """A textured plane ``z = z0 + slope * y`` over ``|x|, |y| <= half``, ray-cast exactly.

    Texture: scikit-image's astronaut (bundled), bilinear. Outside the plane: black, alpha 0.
    """

    def __init__(self, z0: float = 4.0, slope: float = 0.3, half: float = 2.5):
        self.z0, self.slope, self.half = z0, slope, half
        self.tex = skimage.data.astronaut().astype(np.float32) / 255.0  # [512, 512, 3]

    def render(self, world_from_cam, fx, fy, cx, cy, width, height):
        T = np.asarray(world_from_cam, dtype=np.float64)
        u = np.arange(width) + 0.5
        v = np.arange(height) + 0.5
        uu, vv = np.meshgrid(u, v)
        rays = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1)  # z = 1
        d = rays @ T[:3, :3].T
        c = T[:3, 3]
        # (c + t d)_z = z0 + slope (c + t d)_y
        denom = d[..., 2] - self.slope * d[..., 1]
        t = (self.z0 + self.slope * c[1] - c[2]) / np.where(np.abs(denom) < 1e-12, 1e-12, denom)
        X = c + t[..., None] * d
        hit = (t > 1e-6) & (np.abs(X[..., 0]) <= self.half) & (np.abs(X[..., 1]) <= self.half)
        n = self.tex.shape[0]
        mx = ((X[..., 0] + self.half) / (2 * self.half) * n - 0.5).astype(np.float32)
        my = ((X[..., 1] + self.half) / (2 * self.half) * n - 0.5).astype(np.float32)
        mx = np.where(hit, mx, -10).astype(np.float32)
        my = np.where(hit, my, -10).astype(np.float32)
        rgb = cv2.remap(self.tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        alpha = hit.astype(np.float32)
        rgb = rgb * alpha[..., None]
        depth = np.where(hit, t, 0.0).astype(np.float32)
        return rgb.astype(np.float32), depth, alpha


W, H, F = 128, 96, 110.0
K = (F, F, W / 2, H / 2)


def cam(eye, target=(0.0, 0.0, 4.0)):
    return look_at(np.asarray(eye, float), np.asarray(target, float), UP)


def psnr(a, b, mask=None):
    e = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        e = e[mask]
    return float(10 * np.log10(1.0 / max(e.mean(), 1e-12)))


def view_of(world, pose, blur=0.0):
    rgb, depth, alpha = world.render(pose, *K, W, H)
    if blur > 0:
        rgb = cv2.GaussianBlur(rgb, (0, 0), blur)
    return RenderedView(rgb, depth, alpha, pose, *K)


@pytest.fixture(scope="module")
def world():
    return PlaneWorld()


@pytest.fixture(scope="module")
def scene(world):
    """Reference (training) camera, free camera, and their true images."""
    ref_pose = cam([0.0, 0.0, 0.0])
    free_pose = cam([0.5, -0.3, 0.4], target=(0.2, 0.1, 4.0))
    ref_true = world.render(ref_pose, *K, W, H)
    free_true = world.render(free_pose, *K, W, H)
    return ref_pose, free_pose, ref_true, free_true


# --------------------------------------------------------------------------- pose (stage 8)
def _random_pose(rng):
    q = rng.normal(size=4)
    return make_pose(quat_wxyz_to_rotmat(q), rng.normal(size=3) * 3)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000))
def test_pose_rectification_moves_monotonically_toward_reference(seed):
    rng = np.random.default_rng(seed)
    ref, cand = _random_pose(rng), _random_pose(rng)
    poses = rectification_poses(cand, ref, PoseRectifyConfig())
    assert [s for s, _ in poses] == [0.7, 0.5, 0.3]
    d0 = np.linalg.norm(cand[:3, 3] - ref[:3, 3])
    a0 = rotation_angle_deg(cand[:3, :3], ref[:3, :3])
    prev_d, prev_a = d0, a0
    for s, p in poses:
        d = np.linalg.norm(p[:3, 3] - ref[:3, 3])
        a = rotation_angle_deg(p[:3, :3], ref[:3, :3])
        assert d == pytest.approx(s * d0, rel=1e-9, abs=1e-9)
        # slerp: constant angular speed along the short arc
        assert a == pytest.approx(s * a0, abs=1e-5)
        assert d <= prev_d + 1e-12 and a <= prev_a + 1e-6
        # the centre stays on the segment ref -> cand
        assert np.allclose(p[:3, 3], ref[:3, 3] + s * (cand[:3, 3] - ref[:3, 3]))
        assert np.allclose(p[:3, :3] @ p[:3, :3].T, np.eye(3), atol=1e-9)
        prev_d, prev_a = d, a


def test_step_zero_is_the_reference_and_one_the_candidate():
    rng = np.random.default_rng(3)
    ref, cand = _random_pose(rng), _random_pose(rng)
    assert np.allclose(interpolate_pose(ref, cand, 0.0), ref, atol=1e-12)
    assert np.allclose(interpolate_pose(ref, cand, 1.0), cand, atol=1e-12)


def test_world_unit_steps_and_skipping():
    ref = cam([0.0, 0.0, 0.0])
    cand = cam([0.6, 0.0, 0.0])  # 0.6 world units away
    poses = rectification_poses(cand, ref, PoseRectifyConfig(step_unit="world"))
    # 0.7 is not shorter than 0.6: skipped; 0.5 and 0.3 are distances from the reference
    assert [s for s, _ in poses] == [0.5, 0.3]
    for s, p in poses:
        assert np.linalg.norm(p[:3, 3] - ref[:3, 3]) == pytest.approx(s)
    assert rectification_poses(cand, ref, PoseRectifyConfig(enabled=False)) == []


def test_nearest_training_camera_by_centre():
    train = np.stack([cam([x, 0.0, 0.0]) for x in (-2.0, 0.0, 1.0, 1.0)])
    assert nearest_training_camera(train, cam([0.9, 0.2, 0.0])) == 2  # tie 2/3 -> lowest
    assert nearest_training_camera(train, cam([-5.0, 0.0, 0.0])) == 0


# --------------------------------------------------------------------------- references
def _hand_graph():
    # T = 3 training nodes (0, 1, 2); candidates are nodes 3..7
    #   3 - 1 (0.4), 3 - 2 (0.6): direct, best is 2
    #   4 - 5 (0.9), 5 - 0 (0.3); 4 - 6 (0.5), 6 - 1 (0.8): 2-hop, product 0.27 vs 0.40 -> 1;
    #                                               min: 0.3 vs 0.5 -> 1
    #   7: isolated
    src = np.array([3, 2, 4, 5, 6, 1, 3])
    dst = np.array([1, 3, 5, 0, 4, 6, 1])
    w = np.array([0.4, 0.6, 0.9, 0.3, 0.5, 0.8, 0.2])  # (3,1) listed twice: max kept
    return ViewGraph.from_edges(3, 8, src, dst, w)


def test_graph_reference_direct_and_two_hop():
    g = _hand_graph()
    c = graph_reference(g, 3)
    assert (c.train_index, c.rule, c.score) == (2, "graph_direct", 0.6)
    c = graph_reference(g, 4, "product")
    assert (c.train_index, c.rule, c.via) == (1, "graph_2hop", 6)
    assert c.score == pytest.approx(0.4)
    c = graph_reference(g, 4, "min")
    assert (c.train_index, c.via, c.score) == (1, 6, 0.5)
    assert graph_reference(g, 7) is None
    nb, w = g.neighbours(3)
    assert list(nb) == [1, 2] and list(w) == [0.4, 0.6]


def test_two_hop_product_and_min_can_disagree():
    # v=3: path via 4 to 0 with (0.9, 0.35) and via 5 to 1 with (0.5, 0.5)
    g = ViewGraph.from_edges(2, 6, [3, 4, 3, 5], [4, 0, 5, 1], [0.9, 0.35, 0.5, 0.5])
    assert graph_reference(g, 3, "product").train_index == 0  # 0.315 > 0.25
    assert graph_reference(g, 3, "min").train_index == 1  # 0.5 > 0.35


def test_reference_falls_back_to_pose_and_says_so():
    g = _hand_graph()
    train = np.stack([cam([x, 0.0, 0.0]) for x in (-2.0, 0.0, 2.0)])
    free = cam([1.8, 0.1, 0.0])
    c = select_reference(ReferenceConfig(rule="graph"), train, free, g, node=7)
    assert (c.train_index, c.rule) == (2, "pose_fallback")
    c = select_reference(ReferenceConfig(rule="graph"), train, free, None, None)
    assert c.rule == "pose_fallback"
    c = select_reference(ReferenceConfig(rule="pose"), train, free, g, node=3)
    assert (c.train_index, c.rule) == (2, "pose")
    c = select_reference(ReferenceConfig(rule="graph"), train, free, g, node=3)
    assert (c.train_index, c.rule) == (2, "graph_direct")


def test_pose_distance_weighs_rotation():
    # two training cameras equally far; the one looking the same way wins
    a = cam([-1.0, 0.0, 0.0], target=(0.0, 0.0, 4.0))
    b = cam([1.0, 0.0, 0.0], target=(1.0, 0.0, -4.0))  # looking backwards
    free = cam([0.0, 0.0, 0.0])
    d = pose_distances(np.stack([a, b]), free, rotation_weight=1.0)
    assert d[0] < d[1]
    d0 = pose_distances(np.stack([a, b]), free, rotation_weight=0.0)
    assert d0[0] == pytest.approx(d0[1])
    # scale-free: scaling the whole scene leaves the distances unchanged
    s = 7.0
    sc = lambda T: make_pose(T[..., :3, :3], T[..., :3, 3] * s)
    d_s = pose_distances(np.stack([sc(a), sc(b)]), sc(free))
    assert np.allclose(d_s, d)


# --------------------------------------------------------------------------- image (stage 10)
def test_none_rectifier_is_identity(scene, world):
    _, free_pose, _, _ = scene
    v = view_of(world, free_pose, blur=1.5)
    out = NoneRectifier()(v, None, None)
    assert np.array_equal(out.rgb, v.rgb) and np.array_equal(out.depth, v.depth)
    assert not out.weight.any()
    assert make_rectifier(RectifierConfig(backend="none")).name == "none"


def test_reproject_sharpens_blurred_render(scene, world):
    ref_pose, free_pose, ref_true, free_true = scene
    view = view_of(world, free_pose, blur=1.5)
    ref_render = view_of(world, ref_pose, blur=1.5)
    out = ReprojectRectifier()(view, ref_true[0], ref_render)
    before, after = psnr(view.rgb, free_true[0]), psnr(out.rgb, free_true[0])
    assert after > before + 2.0, (before, after)
    assert out.info["frac_consistent"] > 0.5
    # never touches a pixel without reference evidence
    untouched = out.weight == 0
    assert np.array_equal(out.rgb[untouched], view.rgb[untouched])


def test_reproject_fills_a_hole(scene, world):
    ref_pose, free_pose, ref_true, free_true = scene
    view = view_of(world, free_pose, blur=1.0)
    hole = np.zeros((H, W), bool)
    hole[30:60, 40:80] = True
    view.rgb[hole] = 0.0
    view.depth[hole] = 0.0
    view.alpha[hole] = 0.0
    out = ReprojectRectifier()(view, ref_true[0], view_of(world, ref_pose, blur=1.0))
    assert out.info["frac_hole_filled"] > 0.9 * hole.mean()
    assert psnr(out.rgb, free_true[0], hole) > psnr(view.rgb, free_true[0], hole) + 10
    assert np.allclose(out.depth[hole], free_true[1][hole], rtol=0.02)


def test_reproject_removes_a_floater(scene, world):
    ref_pose, free_pose, ref_true, free_true = scene
    view = view_of(world, free_pose)
    fl = np.zeros((H, W), bool)
    fl[40:56, 50:70] = True
    view.rgb[fl] = (1.0, 0.0, 0.0)
    view.depth[fl] *= 0.5  # halfway between camera and plane: empty space for the reference
    out = ReprojectRectifier()(view, ref_true[0], view_of(world, ref_pose))
    assert out.info["frac_carved"] > 0.5 * fl.mean()
    assert psnr(out.rgb, free_true[0], fl) > psnr(view.rgb, free_true[0], fl) + 10


def test_reproject_keeps_render_without_reference_information(scene, world):
    _, free_pose, _, _ = scene
    view = view_of(world, free_pose, blur=1.5)
    away = cam([0.0, 0.0, 0.0], target=(0.0, 0.0, -4.0))  # looks away from the plane
    ref_render = view_of(world, away)
    photo = np.full((H, W, 3), 200, np.uint8)
    out = ReprojectRectifier()(view, photo, ref_render)
    assert not out.weight.any()
    assert np.array_equal(out.rgb, view.rgb)


def test_reproject_respects_occlusion_in_the_reference(scene, world):
    """Where the reference saw something in front of the free view's surface, the free view
    keeps its render (the reference's photo shows the occluder, not the surface)."""
    ref_pose, free_pose, ref_true, _ = scene
    view = view_of(world, free_pose)
    ref_render = view_of(world, ref_pose)
    occ = np.zeros((H, W), bool)
    occ[20:76, 30:90] = True
    ref_render.depth[occ] *= 0.5  # an occluder halfway, seen only by the reference
    photo = (ref_true[0] * 255).astype(np.uint8)
    photo[occ] = (0, 255, 0)
    out = ReprojectRectifier()(view, photo, ref_render)
    green = (out.rgb[..., 1] > 0.9) & (out.rgb[..., 0] < 0.1) & (out.rgb[..., 2] < 0.1)
    assert green.mean() < 0.005


def test_angle_weight_ramp():
    a = np.array([0.0, 5.0, 17.5, 30.0, 90.0, np.nan])
    np.testing.assert_allclose(angle_weight(a, 5.0, 30.0), [1, 1, 0.5, 0, 0, 0])
    np.testing.assert_allclose(angle_weight(a, 10.0, 10.0), [1, 1, 0, 0, 0, 0])


def test_triangulation_angle_of_a_known_point(world):
    free = view_of(world, cam([0.0, 0.0, 0.0]))
    ref = RenderedView(None, None, None, cam([4.0, 0.0, 0.0]), *K)
    depth = np.full((H, W), 4.0)
    ang = triangulation_angle_deg(free, ref, depth)
    # the centre pixel's point is (0, 0, 4): rays from (0, 0, 0) and (4, 0, 0) meet at 45 deg
    assert ang[H // 2, W // 2] == pytest.approx(45.0, abs=1.0)
    assert np.isnan(triangulation_angle_deg(free, ref, np.zeros((H, W)))).all()


def test_reproject_trusts_small_baselines_more(world):
    """A reference far to the side (~60 deg at the plane) is not blended with the default
    angle kernel; without the kernel it is, and a near reference is blended fully."""
    free_pose = cam([1.2, 0.0, 0.0], target=(0.6, 0.0, 4.0))
    view = view_of(world, free_pose, blur=1.5)
    for x, default_blends in ((-3.5, False), (1.0, True)):
        ref_pose = cam([x, 0.0, 0.0], target=(0.3 * x, 0.0, 4.0))
        ref_true = world.render(ref_pose, *K, W, H)
        photo = (ref_true[0] * 255).round().astype(np.uint8)
        on = ReprojectRectifier()(view, photo, view_of(world, ref_pose))
        off = ReprojectRectifier(angle_full_deg=180, angle_zero_deg=180)(
            view, photo, view_of(world, ref_pose))
        assert off.weight.mean() > 0.3
        assert (on.weight.mean() > 0.8 * off.weight.mean()) == default_blends
        assert np.all(on.weight <= off.weight + 1e-6)
    with pytest.raises(ValueError):
        ReprojectRectifier(angle_full_deg=40, angle_zero_deg=10)


def test_rectifier_deterministic(scene, world):
    ref_pose, free_pose, ref_true, _ = scene
    a = ReprojectRectifier()(view_of(world, free_pose, 1.5), ref_true[0], view_of(world, ref_pose))
    b = ReprojectRectifier()(view_of(world, free_pose, 1.5), ref_true[0], view_of(world, ref_pose))
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.weight, b.weight)


def test_difix_unavailable_is_explained():
    with pytest.raises(RectifierUnavailable, match="difix"):
        make_rectifier(RectifierConfig(backend="difix"))


def test_registry_accepts_new_backends():
    class Half(NoneRectifier):
        name = "half"

    register_rectifier("half", Half)
    try:
        assert make_rectifier(RectifierConfig(backend="half")).name == "half"
    finally:
        RECTIFIERS.pop("half")
    with pytest.raises(KeyError, match="unknown rectifier"):
        make_rectifier(RectifierConfig(backend="nope"))


def test_reproject_uses_only_the_reference_photos_mask_pixels(scene, world):
    """A reference photo with an object mask (4th channel): pixels warped from its
    masked-out part are never pasted into the free view."""
    ref_pose, free_pose, ref_true, _ = scene
    view = view_of(world, free_pose, blur=1.5)
    ref_render = view_of(world, ref_pose, blur=1.5)
    photo = ref_true[0]
    H, W = photo.shape[:2]
    a = np.zeros((H, W), np.uint8)
    a[:, : W // 2] = 255  # only the left half is "object"
    full = ReprojectRectifier()(view, photo, ref_render)
    masked = ReprojectRectifier()(view, np.concatenate([photo, a[..., None]], -1), ref_render)
    assert 0 < masked.weight.astype(bool).sum() < 0.8 * full.weight.astype(bool).sum()
    # where the masked run takes nothing from the photo, it keeps the render
    untouched = masked.weight == 0
    assert np.array_equal(masked.rgb[untouched], view.rgb[untouched])
    # an all-255 mask is the same as none
    same = ReprojectRectifier()(view, np.concatenate([photo, np.full((H, W, 1), 255, np.uint8)],
                                                     -1), ref_render)
    np.testing.assert_array_equal(same.rgb, full.rgb)
