"""Visibility and view graph (METHOD.md stage 5, Eq. 3): reference and property tests."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.geometry.cameras import Cameras, look_at
from freescale_core.select.certainty import CertaintyGrid
from freescale_core.select.view_graph import (edges_from_matrix, pose_distance, wiou_block,
                                       wiou_definition, wiou_from_inter, wiou_matrix)
from freescale_core.select.visibility import Visibility, compute_visibility
from schemas.select import VisibilityConfig


def _wiou_loops(W: np.ndarray) -> np.ndarray:
    """Eq. 3 with explicit loops over pairs and voxels (the slowest, most obvious form)."""
    n, K = W.shape
    out = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            mn = sum(min(W[i, k], W[j, k]) for k in range(K))
            mx = sum(max(W[i, k], W[j, k]) for k in range(K))
            out[i, j] = mn / mx if mx > 0 else 0.0
    return out


@st.composite
def _binary_problem(draw):
    n = draw(st.integers(1, 9))
    K = draw(st.integers(1, 40))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    M = rng.random((n, K)) < draw(st.floats(0.0, 1.0))
    C = rng.lognormal(0, 2, K) * (rng.random(K) < 0.9)  # some zero-certainty voxels too
    return M, C


@settings(max_examples=60, deadline=None)
@given(_binary_problem())
def test_gram_form_equals_sum_min_over_sum_max(prob):
    M, C = prob
    vis = Visibility.from_dense(M, C)
    W = wiou_matrix(vis, np.arange(M.shape[0]), np.float64)
    ref = wiou_definition(M * C[None])
    np.testing.assert_allclose(W, ref, atol=1e-9)
    # properties: symmetric, in [0, 1], 1 on the diagonal where f > 0, 0 where f = 0
    np.testing.assert_array_equal(W, W.T)
    assert np.all((W >= 0) & (W <= 1))
    f = M @ C
    np.testing.assert_array_equal(np.diag(W), np.where(f > 0, 1.0, 0.0))
    assert np.all(W[f == 0] == 0)
    # float32 GEMM agrees to float32 accuracy
    np.testing.assert_allclose(wiou_matrix(vis, np.arange(M.shape[0])), ref, atol=2e-5)


def test_definition_matches_explicit_loops():
    rng = np.random.default_rng(4)
    W = rng.random((5, 12)) * (rng.random((5, 12)) < 0.6)  # any non-negative weights
    np.testing.assert_allclose(wiou_definition(W), _wiou_loops(W), atol=1e-12)


def test_wiou_block_matches_matrix_and_zero_over_zero():
    rng = np.random.default_rng(0)
    M = rng.random((12, 300)) < 0.4
    M[3] = False  # a view that sees nothing
    vis = Visibility.from_dense(M, rng.random(300))
    full = wiou_matrix(vis, np.arange(12), np.float64)
    blk = wiou_block(vis, np.array([1, 3, 5]), np.arange(12), np.float64)
    off = full[[1, 3, 5]]
    mask = np.ones_like(off, bool)
    mask[[0, 2], [1, 5]] = False  # block diagonal entries come from the GEMM, not forced to 1
    np.testing.assert_allclose(blk[mask], off[mask], atol=1e-12)
    assert np.all(blk[1] == 0) and np.all(full[3] == 0)
    assert np.all(np.isfinite(wiou_from_inter(np.zeros((2, 2)), np.zeros(2), np.zeros(2))))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), ncell=st.integers(1, 8))
def test_cell_bounds_bracket_the_intersection(seed, ncell):
    rng = np.random.default_rng(seed)
    K = int(rng.integers(ncell, 80))
    M = rng.random((7, K)) < rng.random()
    # make some cells fully visible in some views
    ptr = np.r_[0, np.sort(rng.choice(np.arange(1, K), size=ncell - 1, replace=False)), K] \
        if ncell > 1 else np.array([0, K])
    for c in range(ncell):
        M[rng.random(7) < 0.3, ptr[c]:ptr[c + 1]] = True
    C = rng.lognormal(0, 1, K)
    vis = Visibility.from_dense(M, C, cell_ptr=ptr)
    I = (M * C) @ M.T.astype(float) / vis.norm
    l0, l1 = vis.bound_rows(np.arange(7), "left")
    r0, r1 = vis.bound_rows(np.arange(7), "right")
    L = l0.astype(float) @ r0.T
    U = L + l1.astype(float) @ r1.T
    tol = 1e-5 * (1 + np.abs(I))
    assert np.all(L <= I + tol) and np.all(I <= U + tol)


# ---------------------------------------------------------------------- visibility kernels
def _grid_with_voxels(R=24, seed=0, density=0.08):
    rng = np.random.default_rng(seed)
    vals = (rng.random((R, R, R)) < density) * rng.lognormal(0, 1, (R, R, R))
    return CertaintyGrid(vals.astype(np.float32), [-2.0, -1.0, -0.5], [2.0, 3.0, 1.5])


def _cams(n=30, seed=1):
    rng = np.random.default_rng(seed)
    eye = rng.uniform([-3, -2, -1], [3, 4, 2], (n, 3))
    tgt = rng.uniform([-2, -1, -0.5], [2, 3, 1.5], (n, 3))
    fx = rng.uniform(100, 400, n)
    return Cameras(look_at(eye, tgt, [0, 0, 1]), fx, fx * 1.1, 160.0, 100.0, 320, 200)


@pytest.mark.parametrize("cells", [0, 4])
def test_frustum_visibility_matches_projection(cells):
    grid = _grid_with_voxels()
    cams = _cams()
    cfg = VisibilityConfig(mode="frustum", near=0.01)
    vis = compute_visibility(cams, grid, cfg, cells_per_axis=cells)
    centers = grid.voxel_centers(vis.voxel_idx)
    uv, z = cams.project(centers)
    ref = (z > 0.01 * grid.diagonal) & (uv[..., 0] >= 0) & (uv[..., 0] < cams.width[:, None]) \
        & (uv[..., 1] >= 0) & (uv[..., 1] < cams.height[:, None])
    M = vis.dense()
    assert (M != ref).sum() <= 2  # only pixel-boundary rounding may differ
    assert ref.sum() > 1000
    np.testing.assert_allclose(vis.score, M @ vis.weights, rtol=1e-9)
    np.testing.assert_allclose(vis.weights, grid.values[tuple(vis.voxel_idx.T)], rtol=1e-7)
    if cells:
        ref_vis = Visibility.from_dense(M, vis.weights, cell_ptr=vis.cell_ptr)
        np.testing.assert_array_equal(vis.cell_state, ref_vis.cell_state)
        np.testing.assert_allclose(vis.cell_q, ref_vis.cell_q, rtol=1e-5)


def test_weighted_rows_are_sqrt_weights_times_mask():
    grid = _grid_with_voxels(R=16)
    vis = compute_visibility(_cams(10), grid)
    rows = vis.weighted_rows(np.array([2, 5, 7]), np.float64)
    M = vis.dense(np.array([2, 5, 7]))
    np.testing.assert_allclose(rows, M * np.sqrt(vis.weights / vis.norm), rtol=1e-12)
    part = vis.weighted_rows(np.array([2, 5, 7]), np.float64, 13, 200)  # a voxel range
    np.testing.assert_array_equal(part, rows[:, 13:200])
    full = wiou_matrix(vis, np.arange(10), np.float64)
    np.testing.assert_allclose(wiou_matrix(vis, np.arange(10), np.float64, chunk_voxels=7), full,
                               atol=1e-12)


def test_occlusion_hides_voxels_behind_a_wall():
    R = 32
    vals = np.zeros((R, R, R), np.float32)
    vals[10, 4:28, 4:28] = 1.0   # a wall at ix = 10
    vals[25, 14:18, 14:18] = 5.0  # an object behind it
    grid = CertaintyGrid(vals, [0.0, 0, 0], [8.0, 8, 8])
    eye = np.array([[-4.0, 4.0, 4.0]])
    cams = Cameras(look_at(eye, [[6.5, 4.0, 4.0]], [0, 0, 1]), 200.0, 200.0, 160.0, 120.0, 320, 240)
    fr = compute_visibility(cams, grid, VisibilityConfig(mode="frustum"))
    oc = compute_visibility(cams, grid, VisibilityConfig(mode="occlusion", occluder_quantile=0.0))
    behind = fr.voxel_idx[:, 0] == 25
    front = fr.voxel_idx[:, 0] == 10
    Mf, Mo = fr.dense()[0], oc.dense()[0]
    np.testing.assert_array_equal(fr.voxel_idx, oc.voxel_idx)
    assert Mf[behind].all() and not Mo[behind].any()
    assert Mo[front].sum() >= 0.95 * Mf[front].sum() > 0
    assert oc.score[0] < fr.score[0]


def test_views_that_see_nothing_are_harmless():
    grid = _grid_with_voxels(R=12)
    cams = _cams(4)
    away = Cameras(look_at([[50.0, 50, 50]], [[100.0, 100, 100]], [0, 0, 1]), 100.0, 100.0, 50.0,
                   50.0, 100, 100)  # outside the box, looking away
    allc = Cameras.concat([away, cams])
    vis = compute_visibility(allc, grid, cells_per_axis=3)
    assert vis.score[0] == 0 and not vis.dense()[0].any()
    W = wiou_matrix(vis, np.arange(5))
    assert np.all(W[0] == 0) and np.all(np.isfinite(W))


def test_edges_top_k_threshold_and_unique():
    rng = np.random.default_rng(0)
    S = rng.random((8, 8))
    S = (S + S.T) / 2
    np.fill_diagonal(S, 1.0)
    nodes = np.arange(100, 108)
    src, dst, w = edges_from_matrix(S, nodes, threshold=0.3, top_k=2)
    assert np.all(src < dst) and np.all(w > 0.3)
    pairs = set(zip(src.tolist(), dst.tolist()))
    assert len(pairs) == len(src)
    for i in range(8):  # each node's top-2 (above threshold) are present
        order = [j for j in np.argsort(-S[i]) if j != i and S[i, j] > 0.3][:2]
        for j in order:
            assert (min(nodes[i], nodes[j]), max(nodes[i], nodes[j])) in pairs
    np.testing.assert_allclose(w, S[src - 100, dst - 100])
    src, dst, d = edges_from_matrix(1 - S, nodes, threshold=0.5, top_k=3, larger_is_closer=False)
    assert np.all(d < 0.5)


def test_pose_distance_units():
    base = look_at(np.zeros((1, 3)), [[0.0, 0, 1]], [0, -1, 0])
    R10 = np.eye(4)
    a = np.radians(10)
    R10[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    moved = base.copy()
    moved[0, :3, 3] = [2.0, 0, 0]
    cams = Cameras(np.concatenate([base, base @ R10, moved]), 100.0, 100.0, 50.0, 50.0, 100, 100)
    D = pose_distance(cams, cams, spacing=0.5, rot_unit_deg=10.0)
    np.testing.assert_allclose(np.diag(D), 0, atol=1e-6)
    np.testing.assert_allclose(D, D.T, atol=1e-9)
    assert D[0, 1] == pytest.approx(1.0, rel=1e-6)  # 10 deg = 1 unit
    assert D[0, 2] == pytest.approx(4.0, rel=1e-9)  # 2 / 0.5
