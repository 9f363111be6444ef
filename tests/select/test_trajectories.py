"""Candidate placement (METHOD.md stage 3): modes, determinism, look-at from the grid."""

from __future__ import annotations

import numpy as np
import pytest

from freescale_core.geometry.cameras import Cameras, look_at
from freescale_core.select.certainty import build_certainty_grid
from freescale_core.scene.gaussians import Gaussians
from freescale_core.select.trajectories import (OBJECT_CENTRIC_MODES, central_region, generate_candidates,
                                         lookat_pool, scene_scale, select_anchors, world_up)
from schemas.select import TRAJECTORY_MODES, CandidateConfig, GridConfig


def _scene(n_cams: int = 24, seed: int = 0):
    """A box-shaped object on a floor under a ceiling, cameras on a ring looking at it."""
    rng = np.random.default_rng(seed)
    obj = rng.uniform([-1, -1, 0], [1, 1, 1], (6000, 3))
    face = rng.integers(0, 3, 6000)
    # snap each point to one face of the object box
    side = rng.random(6000) < 0.5
    lo, hi = np.array([-1, -1, 0.0]), np.array([1, 1, 1.0])
    obj[np.arange(6000), face] = np.where(side, lo[face], hi[face])
    floor = np.c_[rng.uniform(-4, 4, (3000, 2)), np.zeros(3000)]
    ceil = np.c_[rng.uniform(-4, 4, (500, 2)), np.full(500, 3.0)]
    pts = np.concatenate([obj, floor, ceil])
    n = len(pts)
    logit = np.r_[np.full(6000, 3.0), np.full(3500, 0.0)]
    logs = np.r_[np.full((6000, 3), np.log(0.01)), np.full((3500, 3), np.log(0.05))]
    g = Gaussians(pts, logs, np.tile([1, 0, 0, 0], (n, 1)), logit, np.zeros((n, 1, 3)))
    t = np.linspace(0, 2 * np.pi, n_cams, endpoint=False)
    eye = np.c_[3 * np.cos(t), 3 * np.sin(t), np.full(n_cams, 1.5)]
    cams = Cameras(look_at(eye, np.zeros((n_cams, 3)) + [0, 0, 0.5], [0, 0, 1]),
                   300.0, 300.0, 160.0, 120.0, 320, 240)
    return g, cams


@pytest.fixture(scope="module")
def scene():
    g, cams = _scene()
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=48))
    return g, cams, grid


def _still(cfg: CandidateConfig) -> CandidateConfig:
    """No anchor jitter, no perturbation: exact geometry checks."""
    return cfg.model_copy(update={"anchor_sigma": (0.0, 0.0), "anchor_rot_deg": 0.0,
                                  "perturb_fraction": 0.0})


def test_paper_settings_give_2000_candidates_of_all_modes(scene):
    _, cams, grid = scene
    cs = generate_candidates(cams, grid, CandidateConfig(), seed=0)
    assert len(cs) == 10 * 10 * 20 >= 2000
    assert set(cs.mode) == set(TRAJECTORY_MODES)
    R = cs.cameras.world_from_cam[:, :3, :3]
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    assert np.all(np.isfinite(cs.cameras.world_from_cam))
    assert cs.perturbed.sum() == round(0.2 * 2000)
    assert len(np.unique(cs.traj_id)) == 100


def test_same_seed_same_cameras(scene):
    _, cams, grid = scene
    cfg = CandidateConfig(n_traj=3, frames_per_traj=6)
    a = generate_candidates(cams, grid, cfg, seed=7)
    b = generate_candidates(cams, grid, cfg, seed=7)
    c = generate_candidates(cams, grid, cfg, seed=8)
    np.testing.assert_array_equal(a.cameras.world_from_cam, b.cameras.world_from_cam)
    np.testing.assert_array_equal(a.cameras.fx, b.cameras.fx)
    np.testing.assert_array_equal(a.lookat, b.lookat)
    assert not np.allclose(a.cameras.world_from_cam, c.cameras.world_from_cam)


def test_lookat_pool_draws_from_high_certainty_voxels(scene):
    _, cams, grid = scene
    cfg = CandidateConfig(n_traj=5, frames_per_traj=4)
    pool, fallback = lookat_pool(grid, cfg.lookat_central_fraction, cfg.lookat_quantile)
    assert len(pool) > 0 and fallback == ""
    vals = grid.values[pool[:, 0], pool[:, 1], pool[:, 2]]
    reg = central_region(grid, cfg.lookat_central_fraction)
    reg_vals = grid.values[reg[:, 0], reg[:, 1], reg[:, 2]]
    assert vals.min() >= np.quantile(reg_vals, cfg.lookat_quantile) > 0
    assert vals.min() >= np.median(grid.values[grid.values > 0])  # high certainty overall too
    cs = generate_candidates(cams, grid, cfg, seed=1)
    oc = np.isin(cs.mode, OBJECT_CENTRIC_MODES)
    assert cs.lookat_pool_size == len(pool)
    assert np.all(np.isfinite(cs.lookat[oc])) and np.all(np.isnan(cs.lookat[~oc]))
    vi = grid.voxel_index(cs.lookat[oc])
    pool_set = {tuple(p) for p in pool}
    assert all(tuple(v) in pool_set for v in vi)
    # the object (high certainty, small opaque Gaussians) is where the targets are
    assert np.all(np.abs(cs.lookat[oc][:, :2]) <= 1.2)


def test_object_centric_frames_look_at_their_target(scene):
    _, cams, grid = scene
    cs = generate_candidates(cams, grid, _still(CandidateConfig(n_traj=4, frames_per_traj=8)), 2)
    oc = np.isin(cs.mode, OBJECT_CENTRIC_MODES)
    c = cs.cameras.centers[oc]
    d = cs.lookat[oc] - c
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(cs.cameras.forward[oc] * d, axis=1), 1.0, atol=1e-9)


def test_mode_geometry(scene):
    _, cams, grid = scene
    cfg = _still(CandidateConfig(n_traj=4, frames_per_traj=10))
    cs = generate_candidates(cams, grid, cfg, seed=3)
    up = world_up(cams)
    np.testing.assert_allclose(up, [0, 0, 1], atol=1e-9)
    for tid in np.unique(cs.traj_id):
        sel = np.flatnonzero(cs.traj_id == tid)
        m = cs.mode[sel[0]]
        c = cs.cameras.centers[sel]
        R = cs.cameras.world_from_cam[sel, :3, :3]
        p = cs.lookat[sel[0]]
        a = cams.centers[cs.anchor_idx[sel[0]]]
        if m.startswith("move_"):
            np.testing.assert_allclose(R, np.broadcast_to(R[0], R.shape), atol=1e-12)
            step = np.diff(c, axis=0)
            if m in ("move_up", "move_down"):
                sgn = 1 if m == "move_up" else -1
                np.testing.assert_allclose(step / np.linalg.norm(step, axis=1, keepdims=True),
                                           np.tile(sgn * up, (len(step), 1)), atol=1e-9)
            else:
                assert np.all(np.abs(step @ up) < 1e-9)
        elif m == "orbit":
            r = np.linalg.norm(c - p, axis=1)
            np.testing.assert_allclose(r, r[0], rtol=1e-9)
            assert 0.3 - 1e-9 <= r[0] / np.linalg.norm(a - p) <= 0.6 + 1e-9
            np.testing.assert_allclose((c - p) @ up, ((c - p) @ up)[0], atol=1e-9)  # same height
        elif m == "lemniscate":
            r = np.linalg.norm(c - p, axis=1)
            np.testing.assert_allclose(r, np.linalg.norm(a - p), rtol=1e-9)
        elif m in ("dolly_in", "dolly_out"):
            dist = np.linalg.norm(c - p, axis=1)
            fx = cs.cameras.fx[sel]
            np.testing.assert_allclose(fx / dist, fx[0] / dist[0], rtol=1e-9)  # same image size
            ratio = dist[-1] / np.linalg.norm(a - p)
            assert ratio == pytest.approx(0.28 if m == "dolly_in" else 1.5, rel=1e-9)
        elif m == "interpolation":
            # on the spline through the training centres: close to the ring of radius 3
            rr = np.linalg.norm(c[:, :2], axis=1)
            assert np.all(np.abs(rr - 3.0) < 0.02) and np.allclose(c[:, 2], 1.5, atol=1e-9)
        # intrinsics: the anchor's principal point and size
        assert np.all(cs.cameras.cx[sel] == cams.cx[cs.anchor_idx[sel[0]]])
        assert np.all(cs.cameras.width[sel] == cams.width[cs.anchor_idx[sel[0]]])


def test_anchors_kmeans_fps_and_few_cameras():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(40, 3))
    for method in ("kmeans", "fps"):
        a = select_anchors(x, 10, method, np.random.default_rng(1))
        assert len(a) == 10 and len(np.unique(a)) == 10
        b = select_anchors(x, 10, method, np.random.default_rng(1))
        np.testing.assert_array_equal(a, b)
    a = select_anchors(x[:3], 10, "kmeans", np.random.default_rng(1))  # fewer cams than N_traj
    assert len(a) == 10 and set(a) == {0, 1, 2}
    # FPS spreads: its 2 anchors are far apart
    a = select_anchors(np.r_[np.zeros((20, 3)) + rng.normal(0, 0.01, (20, 3)), [[10, 0, 0]]], 2,
                       "fps", np.random.default_rng(0))
    assert 20 in a


def test_scale_units_positive_and_single_camera(scene):
    g, cams, grid = scene
    for unit in ("camera_radius", "box_diagonal", "camera_spacing"):
        assert scene_scale(cams, grid, unit) > 0
    one = cams.subset([0])
    assert scene_scale(one, grid, "camera_radius") == pytest.approx(0.05 * grid.diagonal)
    cs = generate_candidates(one, grid, CandidateConfig(n_traj=2, frames_per_traj=3), seed=0)
    assert len(cs) == 60 and np.all(np.isfinite(cs.cameras.world_from_cam))
