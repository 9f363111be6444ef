"""NMS (METHOD.md stage 6): the fast blocked/pruned version equals the plain rule."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.geometry.cameras import Cameras, look_at
from freescale_core.select.nms import nms_pose_distance, nms_reference, nms_wiou, top_k_by_score
from freescale_core.select.view_graph import pose_distance, wiou_definition
from freescale_core.select.visibility import Visibility


def _clustered_problem(seed: int, n_train: int, n_cand: int, K: int, n_cells: int):
    """Views that see contiguous voxel ranges (so overlaps are real and often >= 0.7)."""
    rng = np.random.default_rng(seed)
    N = n_train + n_cand
    start = rng.integers(0, K, N)
    length = rng.integers(1, max(2, K // 2), N)
    k = np.arange(K)
    M = ((k[None] - start[:, None]) % K) < length[:, None]
    M &= rng.random((N, K)) > rng.uniform(0, 0.2)  # holes
    M[rng.random(N) < 0.05] = False  # some views see nothing
    C = rng.lognormal(0, 1.5, K)
    ptr = None
    if n_cells > 1:
        ptr = np.unique(np.r_[0, np.sort(rng.integers(1, K, n_cells - 1)), K])
    return Visibility.from_dense(M, C, cell_ptr=ptr), M, C


def _assert_same(a, b):
    np.testing.assert_array_equal(a.selected, b.selected)
    np.testing.assert_array_equal(a.status, b.status)
    np.testing.assert_array_equal(a.reason, b.reason)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_train=st.integers(0, 6), n_cand=st.integers(0, 40),
       K=st.integers(4, 120), n_cells=st.sampled_from([0, 3, 12]),
       block=st.sampled_from([1, 3, 16, 256]), max_views=st.integers(0, 30),
       thr=st.sampled_from([0.3, 0.7, 0.95]))
def test_fast_nms_equals_plain_rule(seed, n_train, n_cand, K, n_cells, block, max_views, thr):
    vis, M, C = _clustered_problem(seed, n_train, n_cand, K, n_cells)
    N = n_train + n_cand
    W = wiou_definition(M * C[None])
    cand = np.arange(n_train, N)
    ref = nms_reference(W, vis.score, n_train, cand, thr, max_views)
    fast = nms_wiou(vis, n_train, cand, thr, max_views, block_rows=block, dtype=np.float64)
    _assert_same(fast, ref)
    # properties of the result (with the exact WIoU)
    kept = np.r_[np.arange(n_train), fast.selected].astype(int)
    sel = fast.selected
    if len(sel) > 1:
        Wk = W[np.ix_(sel, sel)]
        assert np.all(Wk[~np.eye(len(sel), dtype=bool)] < thr)
    if n_train and len(sel):
        assert np.all(W[np.ix_(sel, np.arange(n_train))] < thr)
    for c in np.flatnonzero(fast.reason == "overlap"):
        assert W[c, kept].max() >= thr  # suppressed by a kept view
        assert fast.overlap[c] >= thr
    assert len(sel) <= max_views
    assert np.all(fast.overlap[sel] < thr)


def test_order_budget_and_zero_score():
    rng = np.random.default_rng(0)
    M = np.eye(6, 30, dtype=bool)  # disjoint views: nothing overlaps
    M = np.repeat(M, 5, axis=1)[:, :30]
    M[5] = False  # zero score
    vis = Visibility.from_dense(M, rng.random(30) + 0.1)
    res = nms_wiou(vis, 1, np.arange(1, 6), 0.7, max_views=2)
    order = 1 + np.argsort(-vis.score[1:5])
    np.testing.assert_array_equal(res.selected, order[:2])
    assert set(res.reason[order[2:]]) == {"budget"} and res.reason[5] == "zero_score"
    assert res.status[0] == "train" and set(res.status[1:]) == {"free_view", "suppressed"}


def test_top_k_by_score():
    score = np.array([5.0, 1.0, 3.0, 0.0, 2.0, 4.0])
    res = top_k_by_score(score, 1, np.arange(1, 6), max_views=2)
    np.testing.assert_array_equal(res.selected, [5, 2])
    assert res.reason[3] == "zero_score" and res.reason[4] == "budget"


def _ring_cams(n, radius, seed):
    rng = np.random.default_rng(seed)
    t = rng.uniform(0, 2 * np.pi, n)
    eye = np.c_[radius * np.cos(t), radius * np.sin(t), rng.normal(0, 0.2, n)]
    return Cameras(look_at(eye, np.zeros((n, 3)), [0, 0, 1]), 100.0, 100.0, 50.0, 50.0, 100, 100)


def test_pose_distance_nms_properties_and_determinism():
    cams = Cameras.concat([_ring_cams(8, 3.0, 0), _ring_cams(120, 3.0, 1)])
    cand = np.arange(8, 128)
    a = nms_pose_distance(cams, 8, cand, spacing=0.3, threshold=3.5, max_views=500, seed=5)
    b = nms_pose_distance(cams, 8, cand, spacing=0.3, threshold=3.5, max_views=500, seed=5)
    _assert_same(a, b)
    D = pose_distance(cams, cams, 0.3, 10.0)
    kept = np.r_[np.arange(8), a.selected]
    for s in a.selected:
        others = kept[kept != s]
        # accepted views are >= threshold from every view kept before them (training + earlier)
        before = np.r_[np.arange(8), a.selected[:list(a.selected).index(s)]]
        assert D[s, before].min() >= 3.5
        assert len(others)
    for c in np.flatnonzero(a.reason == "overlap"):
        assert D[c, kept].min() < 3.5
    assert 0 < len(a.selected) < 120


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_real_visibility_fast_equals_plain(dtype):
    from freescale_core.select.certainty import CertaintyGrid
    from freescale_core.select.visibility import compute_visibility

    rng = np.random.default_rng(3)
    R = 24
    vals = (rng.random((R, R, R)) < 0.05) * rng.lognormal(0, 1, (R, R, R))
    grid = CertaintyGrid(vals.astype(np.float32), [-2.0, -2, -2], [2.0, 2, 2])
    cams = _ring_cams(90, 3.0, 2)
    vis = compute_visibility(cams, grid, cells_per_axis=6)
    W = wiou_definition(vis.dense() * vis.weights[None])
    ref = nms_reference(W, vis.score, 10, np.arange(10, 90), 0.7, 30)
    fast = nms_wiou(vis, 10, np.arange(10, 90), 0.7, 30, block_rows=16, dtype=dtype)
    _assert_same(fast, ref)
    assert fast.stats["bound_pairs"] > 0 and fast.stats["exact_pairs"] < 10 * 80
