"""Co-visibility masks (freescale_core.eval.covis): a pixel loop as reference, planes and an
occluder with known answers, the oracle's masks against a reference model's, and the masked
held-out evaluation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.eval.covis import backproject, covisible_masks, reference_depths
from freescale_core.geometry.cameras import Cameras, look_at


def _cams(eyes, targets, w=12, h=9, f=10.0) -> Cameras:
    n = len(eyes)
    wfc = look_at(np.asarray(eyes, float), np.asarray(targets, float), np.array([0, 0, 1.0]))
    return Cameras(wfc, np.full(n, f), np.full(n, f), np.full(n, w / 2), np.full(n, h / 2),
                   np.full(n, w, np.int64), np.full(n, h, np.int64))


def _plane_depth(cams: Cameras, j: int, z0: float = 0.0) -> np.ndarray:
    """Camera-z depth of the plane z = z0 through each pixel centre (0 where the ray misses)."""
    H, W = int(cams.height[j]), int(cams.width[j])
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    dirs = np.stack([(xs - cams.cx[j]) / cams.fx[j], (ys - cams.cy[j]) / cams.fy[j],
                     np.ones_like(xs)], -1)  # camera rays with z = 1
    R, t = cams.world_from_cam[j][:3, :3], cams.world_from_cam[j][:3, 3]
    dw = dirs @ R.T
    s = (z0 - t[2]) / np.where(np.abs(dw[..., 2]) < 1e-12, np.nan, dw[..., 2])
    return np.where(np.isfinite(s) & (s > 0), s, 0.0)


def _loop(test, test_depth, train, train_depth, rel_tol, no_depth_covered):
    """The obvious implementation: one pixel, one training view at a time."""
    out = []
    for j in range(len(test)):
        H, W = test_depth[j].shape
        m = np.zeros((H, W), bool)
        for y in range(H):
            for x in range(W):
                d = test_depth[j][y, x]
                if not d > 0:
                    m[y, x] = no_depth_covered
                    continue
                xc = np.array([(x + 0.5 - test.cx[j]) / test.fx[j] * d,
                               (y + 0.5 - test.cy[j]) / test.fy[j] * d, d])
                X = test.world_from_cam[j][:3, :3] @ xc + test.world_from_cam[j][:3, 3]
                for i in range(len(train)):
                    c = train.cam_from_world[i]
                    p = c[:3, :3] @ X + c[:3, 3]
                    if p[2] <= 1e-6:
                        continue
                    u = train.fx[i] * p[0] / p[2] + train.cx[i]
                    v = train.fy[i] * p[1] / p[2] + train.cy[i]
                    if not (0 <= u < train.width[i] and 0 <= v < train.height[i]):
                        continue
                    dt = train_depth[i][int(v), int(u)]
                    if dt > 0 and abs(dt - p[2]) <= rel_tol * p[2]:
                        m[y, x] = True
                        break
        out.append(m)
    return out


def test_a_training_view_covers_itself_and_nothing_behind_it():
    cams = _cams([[0, 0, 5], [1, 0, 5]], [[0, 0, 0], [1, 0, 0]])
    d = [_plane_depth(cams, 0), _plane_depth(cams, 1)]
    assert all(x > 0 for x in (d[0].min(), d[1].min()))
    m = covisible_masks(cams.subset([0]), d[:1], cams, d)
    assert m[0].all()
    # a training view looking away sees none of it
    away = _cams([[0, 0, 5]], [[0, 0, 10]])
    m = covisible_masks(cams.subset([0]), d[:1], away, [np.full((9, 12), 3.0)])
    assert not m[0].any()


def test_an_occluder_hides_what_it_covers():
    test = _cams([[0, 0, 5]], [[0, 0, 0]])
    train = _cams([[0.5, 0, 5]], [[0.5, 0, 0]])
    td, trd = _plane_depth(test, 0), _plane_depth(train, 0)
    occluded = trd.copy()
    occluded[:, :6] = 1.0  # something 1 m in front of the camera over its left half
    full = covisible_masks(test, [td], train, [trd])[0]
    part = covisible_masks(test, [td], train, [occluded])[0]
    assert full.sum() > part.sum() > 0
    assert not (part & ~full).any()
    # the pixels lost are exactly those landing in the occluded columns of the training view
    X = backproject(test, 0, td)
    uv, _ = train.project(X)
    lands_left = (uv[0, :, 0] < 6).reshape(td.shape)
    assert np.array_equal(full & ~part, full & lands_left)


def test_pixels_without_depth():
    cams = _cams([[0, 0, 5]], [[0, 0, 0]])
    d = _plane_depth(cams, 0)
    d[0, :] = 0.0
    d[1, 0] = np.inf
    m = covisible_masks(cams, [d], cams, [_plane_depth(cams, 0)])[0]
    assert not m[0].any() and not m[1, 0] and m[2:].all()
    m = covisible_masks(cams, [d], cams, [_plane_depth(cams, 0)], no_depth_covered=True)[0]
    assert m.all()
    with pytest.raises(ValueError, match="depth maps"):
        covisible_masks(cams, [d, d], cams, [d])


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), tol=st.sampled_from([0.01, 0.05, 0.2]),
       sky=st.booleans())
def test_vectorised_equals_the_pixel_loop(seed, tol, sky):
    rng = np.random.default_rng(seed)
    eyes = rng.uniform([-2, -2, 3], [2, 2, 6], (4, 3))
    targets = rng.uniform([-1, -1, 0], [1, 1, 0], (4, 3))
    cams = _cams(eyes, targets, w=7, h=5)
    depths = [_plane_depth(cams, j) * rng.uniform(0.97, 1.03, (5, 7)) for j in range(4)]
    depths[0][rng.random((5, 7)) < 0.2] = 0.0
    test, train = cams.subset([0, 1]), cams.subset([2, 3])
    got = covisible_masks(test, depths[:2], train, depths[2:], tol, sky)
    want = _loop(test, depths[:2], train, depths[2:], tol, sky)
    for g, w in zip(got, want):
        assert np.array_equal(g, w)


def _surface_gaussians(world, cams: Cameras, step: int = 1):
    """Small opaque Gaussians on the oracle's surface, seen from ``cams`` (a stand-in for a
    reference reconstruction whose geometry is right)."""
    from freescale_core.scene.gaussians import Gaussians

    pts, cols = [], []
    for j in range(len(cams)):
        rgb, d = world.render(cams.world_from_cam[j], cams.fx[j], cams.fy[j], cams.cx[j],
                              cams.cy[j], int(cams.width[j]), int(cams.height[j]))
        X = backproject(cams, j, np.maximum(d, 1e-6))[(d > 0).reshape(-1)][::step]
        pts.append(X)
        cols.append(rgb.reshape(-1, 3)[(d > 0).reshape(-1)][::step])
    X = np.concatenate(pts).astype(np.float32)
    n = len(X)
    # scale ~ one pixel's footprint at the scenes' depths (a few metres, f ~ 40 px)
    sh = ((np.concatenate(cols) / 255.0 - 0.5) / 0.28209479).astype(np.float32)[:, None, :]
    return Gaussians(X, np.full((n, 3), np.log(0.03), np.float32),
                     np.tile(np.float32([1, 0, 0, 0]), (n, 1)), np.full(n, 6.0, np.float32), sh)


def test_a_reference_with_the_right_geometry_gives_the_oracle_masks(tmp_path):
    """The reference path (render depth where alpha >= 0.5, cut masks at 5%) on Gaussians laid
    on the true surface of a scene-family arc (180 degrees, OOD split: 20-30% of the held-out
    pixels unseen) finds the oracle's unseen pixels: recall and precision >= 0.7 off the sky,
    and agreement well above the trivial all-covered mask."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from benchmarks.recon import oracle_covis
    from freescale_core.eval.covis import split_masks
    from freescale_core.scene.family import write_family
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import SampleWorld
    from schemas.scene_family import SceneFamilyConfig

    fam = SceneFamilyConfig(layout="random", textures="mixed", path="arc", arc_deg=180)
    write_family(tmp_path / "fam", 1, seed=100, family=fam, n_views=13, width=64, height=48,
                 prefix="arc")
    d = tmp_path / "fam" / "arc_0000"
    scene = load_scene(d, cache_dir=tmp_path / "c")
    world = SampleWorld.load(d)
    train, test = scene.split("ood")
    _, depths, exact = oracle_covis(d, scene, train, test, 1.0)
    te = scene.cameras.subset(test)
    solid = [dd > 0 for dd in depths]
    ref = split_masks(scene, "ood", 1.0, _surface_gaussians(world, scene.cameras), rel_tol=0.05)
    unseen = np.concatenate([~e[s] for e, s in zip(exact, solid)])
    found = np.concatenate([~r[s] for r, s in zip(ref, solid)])
    assert unseen.mean() >= 0.15  # something to find
    recall = (found & unseen).sum() / unseen.sum()
    precision = (found & unseen).sum() / found.sum()
    agree = (found == unseen).mean()
    assert recall >= 0.7 and precision >= 0.7, (recall, precision)
    assert agree >= (1 - unseen.mean()) + 0.1, agree
    assert all((dd > 0).mean() > 0.5 for dd in reference_depths(
        _surface_gaussians(world, scene.cameras), te))


def test_evaluate_and_baselines_score_only_the_given_pixels(tmp_path):
    """``evaluate(masks=...)`` and ``trivial_heldout_baselines(masks=...)`` score the given
    pixels: all-true masks change nothing, a half mask gives the PSNR of that half computed by
    hand, and a mask of the wrong size is refused with the scene's name."""
    import torch

    from freescale_core.eval.heldout import trivial_heldout_baselines
    from freescale_core.raster import render_gaussians
    from freescale_core.recon.losses import masked_psnr
    from freescale_core.recon.trainer import _resize, evaluate
    from freescale_core.scene.gaussians import Gaussians
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp_path / "s", n_views=8, width=40, height=30, seed=0)
    scene = load_scene(d, cache_dir=tmp_path / "c")
    train, test = scene.split("ood")
    rng = np.random.default_rng(0)
    n = 300
    g = Gaussians(rng.normal(0, 1, (n, 3)).astype(np.float32),
                  np.full((n, 3), -2.0, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                  np.full(n, 1.0, np.float32), rng.random((n, 1, 3)).astype(np.float32))
    cams = scene.cameras.subset(test)
    full = [np.ones((int(h), int(w)), bool) for w, h in zip(cams.width, cams.height)]
    half = [m.copy() for m in full]
    for m in half:
        m[:, : m.shape[1] // 2] = False
    plain = evaluate(g, scene, test)
    assert evaluate(g, scene, test, masks=full)["psnr"] == plain["psnr"]
    got = evaluate(g, scene, test, masks=half)["psnr"]
    for j, i in enumerate(test):
        rgb, _, _ = render_gaussians(g, cams.world_from_cam[j], cams.fx[j], cams.fy[j],
                                     cams.cx[j], cams.cy[j], int(cams.width[j]),
                                     int(cams.height[j]))
        ref = _resize(scene.load_image(int(i)), int(cams.width[j]), int(cams.height[j]))
        want = masked_psnr(torch.from_numpy(rgb).double(), torch.from_numpy(ref).double() / 255,
                           torch.from_numpy(half[j]))
        assert got[j] == pytest.approx(want, abs=1e-9)
        assert got[j] != pytest.approx(plain["psnr"][j], abs=1e-6)
    with pytest.raises(ValueError, match=scene.scene_id):
        evaluate(g, scene, test, masks=[m[:-1] for m in full])
    side = int(max(cams.width.max(), cams.height.max()))
    b0 = trivial_heldout_baselines(scene, train, test, side)
    assert trivial_heldout_baselines(scene, train, test, side, full) == b0
    assert trivial_heldout_baselines(scene, train, test, side, half) != b0
    with pytest.raises(ValueError, match=scene.scene_id):
        trivial_heldout_baselines(scene, train, test, side, [m[:-1] for m in full])
