"""Gaussians stay in the scene: the robust bound, the relocation of escaped / oversized
Gaussians, and the extent report."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.recon.bounds import SceneBounds, extent_report, flag_outliers, views_seeing
from freescale_core.recon.trainer import prepare, train
from freescale_core.recon.views import ViewCamera
from schemas.recon import ReconConfig


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp_path_factory.mktemp("bd") / "sample", n_views=8, width=64,
                           height=48, seed=0, n_points=300)
    return load_scene(d)


def test_bound_ignores_stray_points():
    rng = np.random.default_rng(0)
    cams = rng.uniform(-1, 1, (10, 3))
    pts = rng.uniform(-2, 2, (1000, 3))
    b0 = SceneBounds.from_inputs(cams, pts)
    stray = np.concatenate([pts, [[1e4, 0, 0], [0, -1e5, 0]]])
    b1 = SceneBounds.from_inputs(cams, stray)
    assert abs(b1.radius - b0.radius) < 0.05 * b0.radius
    assert 2.5 < b0.radius < 3.6  # half-diagonal of a ~[-2, 2]^3 box


@settings(max_examples=30, deadline=None)
@given(st.floats(0.5, 50.0), st.floats(1.5, 10.0))
def test_flag_escaped_matches_distance(dist, margin):
    b = SceneBounds(np.zeros(3), 1.0)
    means = torch.tensor([[dist, 0.0, 0.0], [0.0, 0.1, 0.0]], dtype=torch.float64)
    params = {"means": means, "log_scales": torch.full((2, 3), -3.0)}
    out = flag_outliers(params, b, margin, None)
    assert (0 in out["escaped"]) == (dist > margin)
    assert 1 not in out["escaped"]


def test_flag_world_and_screen_size():
    b = SceneBounds(np.zeros(3), 1.0)
    params = {"means": torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 2.0], [0.0, 0.0, -2.0]]),
              "log_scales": torch.log(torch.tensor([[0.5] * 3, [0.01] * 3, [0.5] * 3]))}
    cam = ViewCamera(np.eye(4), 50.0, 50.0, 32.0, 24.0, 64, 48)
    out = flag_outliers(params, b, None, 0.2, 0.5, cam)
    assert out["world_scale"].tolist() == [0, 2]
    assert out["screen"].tolist() == [0]  # 3*0.5*50/2 = 37.5 px > 32 px; row 2 is behind


def _views_seeing_obvious(means, cams):
    """Per point and camera: transform, check depth, divide, check the pixel range."""
    out = []
    for X in np.asarray(means, np.float64):
        n = 0
        for i in range(len(cams)):
            R, t = cams.world_from_cam[i][:3, :3], cams.world_from_cam[i][:3, 3]
            x, y, z = R.T @ (X - t)
            if z > 0:
                u, v = cams.fx[i] * x / z + cams.cx[i], cams.fy[i] * y / z + cams.cy[i]
                n += int(0 <= u < cams.width[i] and 0 <= v < cams.height[i])
        out.append(n)
    return np.array(out)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_views_seeing_matches_the_obvious_loop(tiny, seed):
    rng = np.random.default_rng(seed)
    lo, hi = tiny.cameras.centers.min(0), tiny.cameras.centers.max(0)
    pts = rng.uniform(lo - (hi - lo), hi + (hi - lo), (200, 3))
    assert views_seeing(pts, tiny.cameras).tolist() == _views_seeing_obvious(pts,
                                                                             tiny.cameras).tolist()


def test_flag_few_views():
    from freescale_core.geometry.cameras import Cameras

    # two cameras at x = -1 and x = +1 looking down +z, 90-degree field of view
    T = np.repeat(np.eye(4)[None], 2, 0)
    T[0, 0, 3], T[1, 0, 3] = -1.0, 1.0
    cams = Cameras(T, np.full(2, 32.0), np.full(2, 32.0), np.full(2, 32.0), np.full(2, 32.0),
                   np.full(2, 64), np.full(2, 64))
    means = torch.tensor([[0.0, 0.0, 5.0],     # both see it
                          [-3.0, 0.0, 2.5],    # only the left camera
                          [0.0, 0.0, -1.0],    # behind both
                          [0.0, 0.0, 0.5]])    # in front of both, outside both images
    params = {"means": means, "log_scales": torch.full((4, 3), -3.0)}
    b = SceneBounds(np.zeros(3), 1.0)
    assert views_seeing(means, cams).tolist() == [2, 1, 0, 0]
    assert flag_outliers(params, b, None, None, min_views=2, cams=cams)["few_views"].tolist() \
        == [1, 2, 3]
    assert flag_outliers(params, b, None, None, min_views=1, cams=cams)["few_views"].tolist() \
        == [2, 3]
    assert len(flag_outliers(params, b, None, None)["few_views"]) == 0
    # with a size condition: only the few-view Gaussians larger than 10x the median
    params["log_scales"] = torch.log(torch.tensor([[0.1] * 3, [0.1] * 3, [0.1] * 3, [5.0] * 3]))
    assert flag_outliers(params, b, None, None, min_views=2, cams=cams,
                         min_views_size=10.0)["few_views"].tolist() == [3]


def _escape_run(scene, bounds_every, at=5, margin=None):
    """Throw 5 Gaussians 100 bound radii away at step ``at``, train on."""
    cfg = ReconConfig.fast().model_copy(update=dict(
        max_iterations=30, min_iterations=30, densify_from=10, densify_every=10,
        densify_until=20, budget_min=200, cap_gaussians=300, threads=1, train_eval_views=2,
        bounds_every=bounds_every, bounds_margin=margin or ReconConfig.fast().bounds_margin))
    data = prepare(scene, cfg, [0, 2, 4, 6])

    def throw(step, state, info):
        if step == at:
            with torch.no_grad():
                c = torch.from_numpy(data.bounds.centre).float()
                state.params["means"].data[:5] = c + 100.0 * data.bounds.radius * torch.tensor(
                    [1.0, 0.0, 0.0])
    r = train(data, cfg, seed=0, on_step=[throw])
    return r, extent_report(r.gaussians.means, data.bounds)


def test_escaped_gaussians_are_relocated(tiny):
    r_off, e_off = _escape_run(tiny, 0)
    assert e_off["farthest"] > 50  # reproduces the escape without the guard
    r_on, e_on = _escape_run(tiny, 10)
    assert e_on["farthest"] <= 3.0 and e_on["share_beyond"] == 0.0
    assert r_on.stats["mcmc"]["relocated_out_of_bounds"]["escaped"] >= 5
    assert r_on.stats["gaussian_extent"]["farthest"] == pytest.approx(e_on["farthest"])


def test_cpu_preset_margin_still_catches_escapes(tiny):
    """The cpu preset relocates at 10 bound radii (not 3): Gaussians thrown to 100 R still
    come back inside it."""
    m = ReconConfig.cpu().bounds_margin
    assert m is not None and 3.0 < m <= 10.0
    r, e = _escape_run(tiny, 10, margin=m)
    assert e["farthest"] <= m and r.stats["mcmc"]["relocated_out_of_bounds"]["escaped"] >= 5


def test_fountain_gaussians_stay_in_the_scene():
    """strecha_fountain-P11 (unit ~14): with the MCMC noise in world units (the trainer before
    issue 17) Gaussians flew off within ~100 steps (cpu preset: 1.3% beyond 5 R, farthest
    170 R after 158 steps); scale-invariant noise and the bound keep every Gaussian inside."""
    from tests.conftest import real_scene_dir
    from freescale_core.scene.io import load_scene

    scene = load_scene(real_scene_dir("strecha_fountain-P11"))
    train_idx = scene.split("ood")[0]
    # the fast preset's schedule (300 steps; the noise needs the lr of a 300-step schedule and
    # Gaussians that turned transparent), at 64 px to stay cheap
    from lab.legacy import WorldUnitsMCMC  # the old trainer's MCMC, a plug-in of today's loop

    base = dict(threads=1, max_long_side=64)
    cfg_old = ReconConfig.fast().model_copy(update=dict(base, bounds_every=0))
    cfg_new = ReconConfig.fast().model_copy(update=base)
    old = train(scene, cfg_old, seed=0, train_idx=train_idx,
                strategy=WorldUnitsMCMC(cfg_old)).stats["gaussian_extent"]
    new = train(scene, cfg_new, seed=0, train_idx=train_idx).stats["gaussian_extent"]
    print("extent old", old, "new", new)
    assert old["farthest"] > 5.0  # the escape reproduces without the fix
    assert new["farthest"] <= cfg_new.bounds_margin + 0.5 and new["share_beyond"] == 0.0


def test_gaussians_escaping_after_the_last_check_are_dropped(tiny):
    r, e = _escape_run(tiny, 10, at=30)  # thrown after the step-30 check, the last step
    assert r.stats["dropped_out_of_bounds"] >= 5
    assert e["farthest"] <= 3.0 and len(r.gaussians) == r.stats["n_gaussians"]


@pytest.mark.parametrize("min_views", [None, 2])
def test_gaussians_one_view_sees_are_relocated(tiny, min_views):
    """Put 5 Gaussians where exactly one training view sees them (just in front of it); with
    ``prune_min_views=2`` the next check (step 10) moves them onto Gaussians two views see."""
    cfg = ReconConfig.fast().model_copy(update=dict(
        max_iterations=12, min_iterations=12, densify_from=100, budget_min=200, threads=1,
        train_eval_views=2, bounds_every=10, bounds_margin=None, prune_min_views=min_views))
    data = prepare(tiny, cfg, [0, 2, 4, 6])
    c = data.cams
    near = c.centers[0] + 0.02 * data.bounds.radius * c.forward[0]
    assert views_seeing(near[None], c).tolist() == [1]
    seen = {}

    def hook(step, state, info):
        if step == 5:
            with torch.no_grad():
                state.params["means"].data[:5] = torch.from_numpy(near).float()
        if step == 10:
            seen["counts"] = views_seeing(state.params["means"], c)

    r = train(data, cfg, seed=0, on_step=[hook])
    if min_views is None:  # the case reproduces without the rule
        assert (seen["counts"][:5] == 1).all()
    else:
        assert seen["counts"].min() >= 2
        assert r.stats["mcmc"]["relocated_out_of_bounds"]["few_views"] >= 5
