"""Certainty grid (METHOD.md stage 2, Eq. 1): reference, property and storage tests."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.errors import DegenerateSceneError
from freescale_core.scene.gaussians import Gaussians
from freescale_core.select.certainty import (
    CertaintyGrid,
    adaptive_resolution,
    build_certainty_grid,
    scene_box,
)
from schemas.select import GridConfig


def _random_gaussians(n: int, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    return Gaussians(rng.normal(size=(n, 3)) * [3.0, 1.0, 0.5], rng.normal(-2.5, 0.7, (n, 3)),
                     rng.normal(size=(n, 4)), rng.normal(0, 2, n), np.zeros((n, 1, 3)))


def _grid_by_loop(g: Gaussians, R: int, eps: float, margin: float = 0.1) -> np.ndarray:
    """The obvious per-Gaussian loop of Eq. 1 (slow reference)."""
    lo = g.means.astype(np.float64).min(axis=0)
    hi = g.means.astype(np.float64).max(axis=0)
    ext = hi - lo
    bmin, bmax = lo - margin * ext, hi + margin * ext
    C = np.zeros((R, R, R))
    for j in range(len(g)):
        mu = g.means[j].astype(np.float64)
        idx = [min(R - 1, max(0, math.floor((mu[a] - bmin[a]) / (bmax[a] - bmin[a]) * R)))
               for a in range(3)]
        alpha = 1.0 / (1.0 + math.exp(-float(g.opacity_logits[j])))
        vol = math.exp(float(g.log_scales[j, 0])) * math.exp(float(g.log_scales[j, 1])) \
            * math.exp(float(g.log_scales[j, 2]))
        C[idx[0], idx[1], idx[2]] += alpha / (vol + eps)
    return C


def test_grid_matches_per_gaussian_loop():
    g = _random_gaussians(800)
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=9, eps=1e-3, box_quantile=0.0))
    ref = _grid_by_loop(g, 9, 1e-3)
    np.testing.assert_allclose(grid.values, ref, rtol=2e-6, atol=0)
    assert grid.values.dtype == np.float32 and grid.values.shape == (9, 9, 9)


def test_activations_applied_once():
    # one Gaussian: logit 0 -> alpha 0.5; log-scales 0 -> Vol 1. Twice-activated would give
    # sigmoid(0.5) / exp(3 e) instead.
    g = Gaussians(np.zeros((1, 3)), np.zeros((1, 3)), [[1, 0, 0, 0]], [0.0], np.zeros((1, 1, 3)))
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=4, eps=1e-6))
    assert grid.values.sum() == pytest.approx(0.5 / (1 + 1e-6), rel=1e-6)


def test_index_order_is_ix_iy_iz():
    # Gaussians at distinct corners: each must land in the [ix, iy, iz] element of its corner
    pts = np.array([[0.0, 0, 0], [10, 0, 0], [0, 4, 0], [0, 0, 2]])
    logits = np.array([0.0, 1.0, 2.0, 3.0])
    g = Gaussians(pts, np.zeros((4, 3)), np.tile([1, 0, 0, 0], (4, 1)), logits, np.zeros((4, 1, 3)))
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=5))
    a = 1 / (1 + np.exp(-logits)) / (1 + GridConfig().eps)
    for p, val in zip(pts, a):
        ix, iy, iz = grid.voxel_index(p[None])[0]
        assert grid.values[ix, iy, iz] == pytest.approx(val, rel=1e-6)
    assert tuple(grid.voxel_index(pts[1:2])[0]) == (4, 0, 0)
    assert tuple(grid.voxel_index(pts[2:3])[0]) == (0, 4, 0)
    assert tuple(grid.voxel_index(pts[3:4])[0]) == (0, 0, 4)


def test_box_margin_and_degenerate_axes():
    pts = np.array([[0.0, 0, 5], [10, 2, 5]])  # z is flat
    lo, hi = scene_box(pts, margin=0.1)
    np.testing.assert_allclose(lo[:2], [-1.0, -0.2])
    np.testing.assert_allclose(hi[:2], [11.0, 2.2])
    assert hi[2] > lo[2] and (hi[2] - lo[2]) == pytest.approx(0.1 * 1.2)
    lo, hi = scene_box(np.array([[3.0, 3, 3]]))  # a single point: unit box
    assert np.all(hi - lo > 0) and np.all((lo < 3) & (hi > 3))
    g = Gaussians(pts, np.zeros((2, 3)), np.tile([1, 0, 0, 0], (2, 1)), [0, 0], np.zeros((2, 1, 3)))
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=8))
    assert grid.values.sum() > 0 and np.all(grid.voxel_size > 0)


def test_nan_gaussians_raise_scene_error():
    g = _random_gaussians(10)
    g.means[3, 1] = np.nan
    with pytest.raises(DegenerateSceneError, match="scene 'sc1'"):
        build_certainty_grid(g, GridConfig(resolution=8), scene_id="sc1")


@settings(max_examples=40, deadline=None)
@given(R=st.integers(2, 200), seed=st.integers(0, 10_000))
def test_voxel_index_round_trip(R, seed):
    rng = np.random.default_rng(seed)
    lo = rng.normal(0, 100, 3)
    hi = lo + rng.uniform(1e-3, 50, 3)
    grid = CertaintyGrid(np.zeros((R, R, R), np.float32), lo, hi)
    idx = rng.integers(0, R, size=(50, 3))
    np.testing.assert_array_equal(grid.voxel_index(grid.voxel_centers(idx)), idx)
    p = lo + rng.random((50, 3)) * (hi - lo)
    j = grid.voxel_index(p)
    assert np.all((j >= 0) & (j < R))
    vmin = lo + j * grid.voxel_size
    tol = 1e-9 * (np.abs(lo) + np.abs(hi))
    assert np.all(p >= vmin - tol) and np.all(p <= vmin + grid.voxel_size + tol)
    assert np.all(grid.inside_box(p))


def test_adaptive_resolution_range_and_auto():
    g = _random_gaussians(20_000, seed=3)
    lo, hi = scene_box(g.means)
    R, why = adaptive_resolution(g.means, lo, hi, [32, 64, 128, 256], 4.0)
    assert 32 <= R <= 256 and "mean" in why
    grid, R_ad, _ = build_certainty_grid(g, GridConfig(resolution="auto"))
    assert grid.R == R_ad
    # fewer Gaussians -> coarser (or equal) adaptive R
    R_small, _ = adaptive_resolution(g.means[:2000], lo, hi, [32, 64, 128, 256], 4.0)
    assert R_small <= R


def _plane(n: int, seed: int = 0) -> np.ndarray:
    """``n`` centres uniform on the plane z = 0.5 of the unit box (a surface, as a
    reconstruction's Gaussians are): at R the occupied voxels are ~R^2, the mean count per
    occupied voxel is lam / (1 - exp(-lam)) with lam = n / R^2."""
    rng = np.random.default_rng(seed)
    return np.c_[rng.random((n, 2)), np.full(n, 0.5)]


def _mean_rule_R(n: int, target: float = 4.0) -> float:
    """The R at which the expected mean count of :func:`_plane` equals ``target``."""
    from scipy.optimize import brentq

    lam = brentq(lambda x: x / (1.0 - np.exp(-x)) - target, 1e-6, 100.0)
    return float(np.sqrt(n / lam))


def test_adaptive_resolution_is_continuous_between_candidates():
    # 6,300 centres on a plane: the mean per occupied voxel reaches 4 near R = 40, between the
    # candidates 32 and 48. The earlier median rule fell back to the floor here (the median
    # is an integer: 3 at R = 32 < 4), as it did on the evaluation's procedural scenes
    # (docs/EVALUATION.md); the mean rule interpolates in log R and rounds to a multiple of 8.
    lo, hi = np.zeros(3), np.ones(3)
    m = _plane(6300, seed=1)
    R, why = adaptive_resolution(m, lo, hi, [32, 48, 64, 96, 128], 4.0)
    assert R == 40 and abs(R - _mean_rule_R(6300)) < 8
    assert "mean" in why and "R=32" in why and "R=48" in why
    # more Gaussians -> a finer R, through values that are not candidates
    Rs = [adaptive_resolution(_plane(n, seed=2), lo, hi, [32, 48, 64, 96, 128], 4.0)[0]
          for n in (3000, 6300, 12000, 40000)]
    assert Rs == sorted(Rs) and Rs[0] == 32 and 96 < Rs[-1] < 128
    assert sum(r not in (32, 48, 64, 96, 128) for r in Rs) >= 2
    for n, r in zip((6300, 12000, 40000), Rs[1:]):
        assert abs(r - _mean_rule_R(n)) <= 8


def test_adaptive_resolution_floor_and_ceiling_reasons():
    lo, hi = np.zeros(3), np.ones(3)
    R, why = adaptive_resolution(_plane(500), lo, hi, [32, 64, 128], 4.0)
    assert R == 32 and "coarsest" in why  # too few Gaussians even at the floor
    R, why = adaptive_resolution(_plane(400_000), lo, hi, [32, 64, 128], 4.0)
    assert R == 128 and "finest" in why  # the target is met even at the finest candidate
    # candidates outside [32, 256] are clamped
    R, _ = adaptive_resolution(_plane(500), lo, hi, [8, 16], 4.0)
    assert R == 32


def test_zarr_round_trip():
    zarr = pytest.importorskip("zarr")
    g = _random_gaussians(500)
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=16))
    root = zarr.open_group(store=zarr.storage.MemoryStore(), mode="w")
    grid.to_zarr(root)
    assert root["certainty"].shape == (16, 16, 16)
    assert list(root["certainty"].attrs["bbox_min"]) == pytest.approx(list(grid.bbox_min))
    back = CertaintyGrid.from_zarr(root)
    np.testing.assert_array_equal(back.values, grid.values)
    np.testing.assert_array_equal(back.bbox_max, grid.bbox_max)


# --------------------------------------------------------------------------- robustness
def _scene_with_far_gaussians(n: int = 4000, far_fraction: float = 0.3, far: float = 100.0,
                              seed: int = 0):
    """Unit-sized objects seen by a ring of cameras, plus Gaussians thrown ``far`` x out that
    are small and opaque (they hold real certainty, so the mass trim keeps them)."""
    rng = np.random.default_rng(seed)
    n_far = int(n * far_fraction)
    near = rng.uniform(-1, 1, (n - n_far, 3))
    d = rng.normal(size=(n_far, 3))
    far_pts = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.5, 1, (n_far, 1)) * far
    means = np.concatenate([near, far_pts])
    g = Gaussians(means, np.full((n, 3), -3.0), np.tile([1.0, 0, 0, 0], (n, 1)),
                  np.full(n, 3.0), np.zeros((n, 1, 3)))
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    cams = np.stack([3 * np.cos(a), 3 * np.sin(a), np.full_like(a, 0.5)], axis=1)
    pts = rng.uniform(-1, 1, (500, 3))
    return g, cams, pts


@pytest.mark.parametrize("far_fraction", [0.05, 0.3, 0.6])
def test_far_gaussians_cannot_stretch_the_box(far_fraction):
    g, cams, pts = _scene_with_far_gaussians(far_fraction=far_fraction)
    cfg = GridConfig(resolution=32)
    loose, _, _ = build_certainty_grid(g, cfg)
    grid, _, _ = build_certainty_grid(g, cfg, camera_centers=cams, points=pts)
    if far_fraction >= 0.3:  # the old box: tens of times the scene
        assert loose.diagonal > 30 * 2 * math.sqrt(3)
    # cameras + points span 6 x 6 x 2 (diagonal 8.7): the box stays within that widened by
    # a quarter of the diagonal per side
    assert grid.diagonal < 2 * 8.8
    assert np.all(grid.bbox_min >= -3 - 2.2) and np.all(grid.bbox_max <= 3 + 2.2)
    # the objects' certainty is in the grid
    assert grid.lookup(np.zeros((1, 3)))[0] > 0 or grid.values.sum() > 0
    # cameras only (no sparse points, e.g. instant-ngp): still bounded
    grid2, _, _ = build_certainty_grid(g, cfg, camera_centers=cams)
    assert grid2.diagonal < 0.5 * loose.diagonal or far_fraction < 0.3


def test_anchor_box_ignores_nan_and_keeps_gaussian_box_when_disjoint():
    from freescale_core.select.certainty import anchor_box

    cams = np.array([[0, 0, 0], [1, 1, 1], [np.nan, 0, 0]], float)
    lo, hi = anchor_box(cams, None, 1.0)
    assert np.all(np.isfinite(lo)) and np.all(hi > lo)
    # Gaussians entirely outside the capture's box (another frame): box left as is
    g = _random_gaussians(200)
    g.means[:] += 1e4
    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=8), camera_centers=cams)
    assert grid.bbox_min[0] > 1e3


def test_grid_memory_guard_refuses_with_the_estimate():
    from freescale_core.errors import ResourceLimitError

    g = _random_gaussians(100)
    with pytest.raises(ResourceLimitError) as e:
        build_certainty_grid(g, GridConfig(resolution=1024), scene_id="tiny")
    msg = str(e.value)
    assert "tiny" in msg and "select.grid.resolution=1024" in msg and "GB" in msg
    with pytest.raises(ResourceLimitError, match="max_memory_gb=0.01"):
        build_certainty_grid(g, GridConfig(resolution=128, max_memory_gb=0.01), scene_id="t")
    build_certainty_grid(g, GridConfig(resolution=64, max_memory_gb=0.01))  # 4.7 MB: fine


def test_masked_out_space_is_not_certain():
    """Turntable cameras and exact object masks: Gaussians inside the object stay in the
    grid, a shell of background Gaussians around it (seen through masked-out pixels) leaves
    it; without masks the shell is certain."""
    from freescale_core.scene.sample import SampleWorld
    from freescale_core.scene.turntable import (
        render_turntable,
        turntable_path,
        turntable_spec,
    )
    from freescale_core.select.certainty import object_support

    n, W, H = 12, 48, 36
    cams = turntable_path(n, W, H, 0)
    spec = turntable_spec(n, W, H, 0, [f"f{i}.png" for i in range(n)])
    _, masks, _ = render_turntable(spec, SampleWorld(spec).cameras, 0)
    rng = np.random.default_rng(0)
    obj = rng.uniform([-0.25, -0.2, 0.05], [0.25, 0.2, 0.45], (400, 3))  # inside the base box
    a = rng.uniform(0, 2 * np.pi, 400)
    r = rng.uniform(1.0, 1.5, 400)
    shell = np.stack([r * np.cos(a), r * np.sin(a), rng.uniform(0.0, 1.2, 400)], 1)
    means = np.concatenate([obj, shell])
    m = len(means)
    g = Gaussians(means, np.full((m, 3), -3.0), np.tile([1.0, 0, 0, 0], (m, 1)),
                  np.full(m, 2.0), np.zeros((m, 1, 3)))
    keep, counts = object_support(means, cams, lambda i: masks[i], 0.5)
    assert keep[:400].all()
    assert keep[400:].mean() < 0.05
    assert counts["n_gaussians_outside_masks"] == int((~keep).sum())
    cfg = GridConfig(resolution=32, box_anchor_margin=None)
    plain, _, _ = build_certainty_grid(g, cfg)
    masked, _, _ = build_certainty_grid(g.subset(np.flatnonzero(keep)), cfg)
    assert (plain.lookup(shell) > 0).mean() > 0.9
    assert (masked.lookup(shell) > 0).mean() < 0.05
    assert (masked.lookup(obj) > 0).all()
    # all-True masks change nothing
    keep_all, _ = object_support(means, cams, lambda i: np.ones((H, W), bool), 0.5)
    assert keep_all.all()
