"""Trust scores (freescale_core.freeviews.trust): each fast function against an obvious loop
on tiny inputs, plus behaviour checks that can fail."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.freeviews.rectify_image import RenderedView
from freescale_core.freeviews.trust import (FEATURES, TrustScores, bilinear_sample,
                                            certainty_support, depth_edge_share,
                                            floater_share, floater_share_median,
                                            loss_weight, score_trust,
                                            nearest_training_views, photometric_consistency,
                                            photometric_consistency_numpy,
                                            predict_psnr, trust_features, view_angle_deg,
                                            view_angle_deg_numpy)


def _pose(c, yaw=0.0):
    """Camera at ``c`` looking along +z rotated by ``yaw`` about y (OpenCV axes)."""
    cy_, sy = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[cy_, 0, sy], [0, 1, 0], [-sy, 0, cy_]]
    T[:3, 3] = c
    return T


def _view(rng, H=6, W=7, pose=None, f=6.0, depth=None, alpha=None):
    rgb = rng.random((H, W, 3)).astype(np.float32)
    if depth is None:
        depth = (3.0 + rng.random((H, W))).astype(np.float32)
    if alpha is None:
        alpha = np.ones((H, W), np.float32)
    return RenderedView(rgb, depth, alpha, _pose([0, 0, 0]) if pose is None else pose,
                        f, f, W / 2, H / 2)


def _lift1(view, i, j, d):
    x = np.array([(j + 0.5 - view.cx) / view.fx, (i + 0.5 - view.cy) / view.fy, 1.0]) * d
    T = np.asarray(view.world_from_cam)
    return T[:3, :3] @ x + T[:3, 3]


def _proj1(view, X):
    T = np.asarray(view.world_from_cam)
    Xc = T[:3, :3].T @ (X - T[:3, 3])
    return view.fx * Xc[0] / Xc[2] + view.cx, view.fy * Xc[1] / Xc[2] + view.cy, Xc[2]


def _bilinear1(img, x, y):
    H, W = img.shape[:2]
    x, y = min(max(x, 0.0), W - 1.0), min(max(y, 0.0), H - 1.0)
    x0, y0 = int(math.floor(x)), int(math.floor(y))
    x1, y1 = min(x0 + 1, W - 1), min(y0 + 1, H - 1)
    ax, ay = x - x0, y - y0
    return ((1 - ay) * ((1 - ax) * img[y0, x0] + ax * img[y0, x1])
            + ay * ((1 - ax) * img[y1, x0] + ax * img[y1, x1]))


def test_bilinear_matches_loop():
    rng = np.random.default_rng(0)
    img = rng.random((5, 6, 3))
    xs, ys = rng.uniform(-1, 7, 40), rng.uniform(-1, 6, 40)
    got = bilinear_sample(img, xs, ys)
    for k in range(40):
        np.testing.assert_allclose(got[k], _bilinear1(img, xs[k], ys[k]), atol=1e-12)


def _photo_loop(view, refs, alpha_min=0.5, tol=0.03):
    H, W = view.hw
    err = np.full((H, W), np.nan)
    for i in range(H):
        for j in range(W):
            d = float(view.depth[i, j])
            if not (d > 0 and view.alpha[i, j] >= alpha_min):
                continue
            X = _lift1(view, i, j, d)
            es = []
            for photo, ref in refs:
                Hr, Wr = photo.shape[:2]
                u, v, z = _proj1(ref, X)
                if not (z > 1e-9 and 0.5 <= u <= Wr - 0.5 and 0.5 <= v <= Hr - 0.5):
                    continue
                iy, ix = min(int(math.floor(v)), Hr - 1), min(int(math.floor(u)), Wr - 1)
                dr = float(ref.depth[iy, ix])
                if not (dr > 0 and ref.alpha[iy, ix] >= alpha_min and abs(z - dr) <= tol * dr):
                    continue
                w = _bilinear1(photo.astype(np.float64), u - 0.5, v - 0.5)
                es.append(np.mean((w - view.rgb[i, j].astype(np.float64)) ** 2))
            if es:
                err[i, j] = np.mean(es)
    has = np.isfinite(err)
    psnr = -10 * math.log10(err[has].mean()) if has.any() else math.nan
    return psnr, has.mean(), err


def _flat_scene(rng, H=6, W=7):
    """A free view and two references looking at a wall z = 4 (plus noise), references
    rendered with the wall's exact depth, one of them with an occluder patch."""
    view = _view(rng, H, W, pose=_pose([0.05, 0.0, 0.0]),
                 depth=np.full((H, W), 4.0, np.float32))
    view.depth[0, 0] = 0.0  # invalid pixel
    view.alpha[1, 1] = 0.2  # empty pixel
    refs = []
    for c, yaw in (([0.3, 0.1, 0.0], 0.05), ([-0.4, 0.0, 0.2], -0.08)):
        pose = _pose(c, yaw)
        ref = RenderedView(None, None, None, pose, 6.0, 6.0, W / 2, H / 2)
        # exact wall depth in the reference: z-depth of the plane z_world = 4
        dep = np.zeros((H, W), np.float32)
        for i in range(H):
            for j in range(W):
                r = pose[:3, :3] @ np.array([(j + 0.5 - W / 2) / 6, (i + 0.5 - H / 2) / 6, 1])
                dep[i, j] = (4.0 - c[2]) / r[2]
        ref.depth = dep
        ref.alpha = np.ones((H, W), np.float32)
        ref.rgb = rng.random((H, W, 3)).astype(np.float32)
        refs.append(((ref.rgb * 255).astype(np.uint8), ref))
    refs[1][1].depth[2:4, 2:4] = 1.0  # an occluder in front of the wall
    return view, refs


def test_photometric_consistency_matches_loop():
    rng = np.random.default_rng(1)
    view, refs = _flat_scene(rng)
    p, s, e = photometric_consistency(view, refs)
    p0, s0, e0 = _photo_loop(view, [(ph.astype(np.float64) / 255.0, r) for ph, r in refs])
    assert s == pytest.approx(s0) and 0 < s < 1
    np.testing.assert_allclose(e, e0, atol=1e-12, equal_nan=True)
    assert p == pytest.approx(p0, abs=1e-9)


def test_photometric_consistency_identical_photo_is_perfect():
    """The reference's photo is the render of the same camera: the error is 0 -> inf dB."""
    rng = np.random.default_rng(2)
    view = _view(rng)
    p, s, _ = photometric_consistency(view, [(view.rgb, view)])
    assert s == 1.0 and p > 100.0  # round-off only
    p2, s2, _ = photometric_consistency(view, [])
    assert math.isnan(p2) and s2 == 0.0


def test_photometric_occlusion_removes_support():
    rng = np.random.default_rng(3)
    view, refs = _flat_scene(rng)
    _, s_all, _ = photometric_consistency(view, refs[:1])
    ref = refs[0][1]
    ref.depth = np.full_like(ref.depth, 1.0)  # the reference sees something nearer everywhere
    _, s_occ, _ = photometric_consistency(view, refs[:1])
    assert s_all > 0.5 and s_occ == 0.0


def _cert_loop(view, values, lo, hi, high, low, am=0.5):
    H, W = view.hw
    R = values.shape[0]
    cs, beyond = 0.0, 0
    for i in range(H):
        for j in range(W):
            d = float(view.depth[i, j])
            a = float(view.alpha[i, j])
            if not (d > 0 and a >= am):
                beyond += 1
                continue
            X = _lift1(view, i, j, d)
            idx = [int(math.floor((X[k] - lo[k]) * R / (hi[k] - lo[k]))) for k in range(3)]
            if all(0 <= t < R for t in idx):
                c = values[idx[0], idx[1], idx[2]]
                cs += a * (c >= high)
                beyond += c < low
            else:
                beyond += 1
    return cs / (H * W), beyond / (H * W)


def test_certainty_support_matches_loop():
    rng = np.random.default_rng(4)
    view = _view(rng, depth=(2.0 + 3 * rng.random((6, 7))).astype(np.float32),
                 alpha=rng.random((6, 7)).astype(np.float32))
    values = rng.random((5, 5, 5)).astype(np.float32) * (rng.random((5, 5, 5)) > 0.3)
    lo, hi = np.array([-1.5, -1.0, 1.0]), np.array([1.5, 1.0, 4.0])
    got = certainty_support(view, values, lo, hi, 0.5, 0.1)
    want = _cert_loop(view, values, lo, hi, 0.5, 0.1)
    assert got == pytest.approx(want, abs=1e-12)
    assert 0 < got[0] < 1 and 0 < got[1] < 1


def _edges_loop(d, valid, tau):
    H, W = d.shape
    n = e = 0
    for i in range(H):
        for j in range(W):
            if not valid[i, j]:
                continue
            n += 1
            for di, dj in ((0, 1), (0, -1), (1, 0), (-1, 0)):
                a, b = i + di, j + dj
                if 0 <= a < H and 0 <= b < W and valid[a, b] and \
                        abs(d[i, j] - d[a, b]) > tau * min(d[i, j], d[a, b]):
                    e += 1
                    break
    return e / n if n else 0.0


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000))
def test_depth_edges_matches_loop(seed):
    rng = np.random.default_rng(seed)
    d = rng.choice([1.0, 1.05, 2.0, 5.0], size=(5, 6))
    valid = rng.random((5, 6)) > 0.2
    assert depth_edge_share(d, valid, 0.1) == pytest.approx(_edges_loop(d, valid, 0.1))


def _floater_loop(d, valid, window, ratio, stride):
    H, W = d.shape
    far = d[valid].max() * 1e3
    dd = np.where(valid, d, far)
    small = dd[::stride, ::stride]
    w = max(3, 2 * (window // (2 * stride)) + 1)
    r = w // 2
    pad = np.pad(small, r, mode="edge")
    n = 0
    for i in range(H):
        for j in range(W):
            a, b = i // stride, j // stride
            med = np.median(pad[a:a + w, b:b + w])
            n += bool(valid[i, j] and dd[i, j] < ratio * med)
    return n / (H * W)


@pytest.mark.parametrize("stride", [1, 3])
def test_floaters_match_loop_and_find_a_blob(stride):
    rng = np.random.default_rng(5)
    d = 5.0 + rng.random((12, 13))
    d[5:7, 6:8] = 1.0  # a near blob
    valid = rng.random((12, 13)) > 0.1
    valid[5:7, 6:8] = True
    got = floater_share(d, valid, 9, 0.6, stride)
    assert got == pytest.approx(_floater_loop(d, valid, 9, 0.6, stride))
    assert got > 0
    assert floater_share(5.0 + rng.random((12, 13)), np.ones((12, 13), bool), 9, 0.6,
                         stride) == 0.0


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_floater_counting_equals_the_median_filter_on_a_render_sized_depth(stride):
    """The counting kernel (no median formed) against scipy's median filter (the code before
    issue 63) at a realistic size with blobs, ties, empty pixels and image-edge blobs: equal
    exactly (the tolerance is 0: both decide d < ratio * v on the same float64 values)."""
    rng = np.random.default_rng(11)
    H, W = 96, 128
    d = 4.0 + np.round(rng.random((H, W)), 1)  # many ties
    d[20:26, 30:41] = 1.5
    d[0:5, 0:4] = 0.8  # a blob at the corner: edge replication decides it
    d[rng.random((H, W)) < 0.02] = 2.0
    valid = rng.random((H, W)) > 0.15
    valid[60:90, 90:128] = False  # empty region (counts as far)
    for window, ratio in ((15, 0.6), (9, 0.6), (7, 0.5)):
        got = floater_share(d, valid, window, ratio, stride)
        assert got == floater_share_median(d, valid, window, ratio, stride)
    assert floater_share(d, valid, 15, 0.6, stride) > 0


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(3, 17), st.integers(1, 4),
       st.sampled_from([0.3, 0.6, 0.9]), st.integers(1, 14), st.integers(1, 14))
def test_floater_counting_equals_median_property(seed, window, stride, ratio, H, W):
    """Any depth, validity, window, stride and ratio: the counting kernel equals the
    median-filter definition exactly."""
    rng = np.random.default_rng(seed)
    d = rng.choice([0.5, 1.0, 1.0, 2.0, 3.0, 9.0], size=(H, W)) * rng.choice([1.0, 1.01],
                                                                              size=(H, W))
    valid = rng.random((H, W)) > 0.3
    assert (floater_share(d, valid, window, ratio, stride)
            == floater_share_median(d, valid, window, ratio, stride))


def test_score_trust_equals_the_scores_computed_one_by_one():
    """score_trust lifts the view once and shares the points: every score equals the same
    function called on its own (each lifting the view itself, the code before issue 63)."""
    from types import SimpleNamespace

    from schemas.freeview import TrustConfig

    rng = np.random.default_rng(7)
    view, refs = _flat_scene(rng, 12, 14)
    poses = np.stack([r.world_from_cam for _, r in refs])
    intr = tuple(np.full(2, v, np.float64) for v in (6.0, 6.0, 7.0, 6.0, 14.0, 12.0))
    grid = SimpleNamespace(bbox_min=np.array([-3.0, -3.0, 0.0]),
                           bbox_max=np.array([3.0, 3.0, 6.0]))
    dilated = rng.random((6, 6, 6))
    cfg = TrustConfig()
    ctx = SimpleNamespace(cfg=cfg, poses=poses, intr=intr, grid=grid, dilated=dilated,
                          high=0.5, low=0.1, timer=None, ref=lambda i: refs[i])
    got = score_trust(view, ctx, 0.3, 0.05, 0.6)
    ok = (view.depth > 0) & (view.alpha >= cfg.alpha_min)
    near = nearest_training_views(view, poses, *intr, k=cfg.n_refs,
                                  max_angle_deg=cfg.ref_max_angle_deg)
    assert len(near) > 0
    pp, sup, _ = photometric_consistency(view, [refs[i] for i in near], 0.5, cfg.depth_tol)
    cs, bs = certainty_support(view, dilated, grid.bbox_min, grid.bbox_max, 0.5, 0.1)
    want = TrustScores(photo_psnr=pp, photo_support=sup, certain_share=cs, beyond_share=bs,
                       depth_edges=depth_edge_share(view.depth, ok, cfg.edge_tau),
                       floaters=floater_share_median(view.depth, ok, cfg.floater_window,
                                                     cfg.floater_ratio, cfg.floater_stride),
                       view_angle_deg=view_angle_deg(view, poses, *intr))
    want.pred_psnr = float(predict_psnr(trust_features(want, 0.3, 0.05, 0.6)))
    for k, v in want.as_dict().items():
        assert getattr(got, k) == v or (math.isnan(v) and math.isnan(getattr(got, k))), k


def _angle_loop(view, poses, f, W, H, stride):
    vals = []
    for i in range(0, view.hw[0], stride):
        for j in range(0, view.hw[1], stride):
            d = float(view.depth[i, j])
            if not (d > 0 and view.alpha[i, j] >= 0.5):
                continue
            X = _lift1(view, i, j, d)
            a = X - view.world_from_cam[:3, 3]
            best = 180.0
            for P in poses:
                tv = RenderedView(None, None, None, P, f, f, W / 2, H / 2)
                u, v, z = _proj1(tv, X)
                if z > 1e-9 and 0 <= u < W and 0 <= v < H:
                    b = X - P[:3, 3]
                    c = np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b)
                    best = min(best, math.degrees(math.acos(min(1.0, max(-1.0, c)))))
            vals.append(best)
    return float(np.median(vals))


def test_view_angle_matches_loop():
    rng = np.random.default_rng(6)
    view = _view(rng, pose=_pose([0.0, 0.0, 0.0]))
    poses = np.stack([_pose([0.5, 0, 0], -0.1), _pose([-1.0, 0.2, 0.5], 0.2),
                      _pose([0, 0, 8], math.pi)])
    n = len(poses)
    intr = [np.full(n, 6.0), np.full(n, 6.0), np.full(n, 3.5), np.full(n, 3.0),
            np.full(n, 7.0), np.full(n, 6.0)]
    for stride in (1, 2):
        got = view_angle_deg(view, poses, *intr, stride=stride)
        assert got == pytest.approx(_angle_loop(view, poses, 6.0, 7, 6, stride), abs=1e-9)
    assert view_angle_deg(view, poses[:0], *[a[:0] for a in intr]) == 180.0
    # a training camera at the free view's own pose: angle 0
    assert view_angle_deg(view, poses[:1] * 0 + view.world_from_cam, *intr) == \
        pytest.approx(0.0, abs=1e-6)


def test_nearest_training_views_prefers_overlap():
    rng = np.random.default_rng(7)
    view = _view(rng, pose=_pose([0.0, 0.0, 0.0]))
    poses = np.stack([_pose([0, 0, 8], math.pi), _pose([0.2, 0, 0], 0.0),
                      _pose([3.0, 0, 0], -0.7), _pose([0, 0, -20], 0.0)])
    n = len(poses)
    intr = [np.full(n, 6.0), np.full(n, 6.0), np.full(n, 3.5), np.full(n, 3.0),
            np.full(n, 7.0), np.full(n, 6.0)]
    near = nearest_training_views(view, poses, *intr, k=3, stride=1)
    assert near[0] == 1 and 0 not in near  # the one behind the wall sees it at 180 deg


def test_predict_psnr_imputes_and_weights():
    x = trust_features(TrustScores(photo_psnr=30.0, photo_support=0.0), 0.3, 0.1, 0.5)
    assert x.shape == (len(FEATURES),) and x[0] == 5.0  # no support -> the floor
    mean, scale = np.arange(len(FEATURES), dtype=float), np.ones(len(FEATURES))
    coef = np.ones(len(FEATURES))
    f = mean + 1.0
    f[2] = np.nan  # imputed with the mean: contributes 0
    assert predict_psnr(f, mean, scale, coef, 10.0) == pytest.approx(10.0 + len(FEATURES) - 1)
    w = loss_weight(np.array([25.0, 22.0, 40.0, np.nan]), 25.0)
    np.testing.assert_allclose(w, [1.0, 10 ** -0.3, 1.0, 0.0])


# --------------------------------------------------------------------------- in the stage
def test_final_selection_trust_stepwise():
    from schemas.freeview import FinalSelectConfig

    from freescale_core.freeviews.run import final_selection_trust

    p = np.array([27.0, 23.0, 21.0, 25.0, 15.0])
    cfg = FinalSelectConfig(target=3, trust_thresholds=[26.0, 24.0, 22.0, 20.0])
    keep, t, scarce = final_selection_trust(p, cfg)
    assert t == 22.0 and list(np.flatnonzero(keep)) == [0, 1, 3] and not scarce
    cfg = FinalSelectConfig(target=2, cap_to_target=True, trust_thresholds=[20.0])
    keep, t, _ = final_selection_trust(p, cfg)
    assert list(np.flatnonzero(keep)) == [0, 3]
    keep, t, scarce = final_selection_trust(p, FinalSelectConfig(target=9))
    assert keep.all() and math.isnan(t) and scarce


def test_stage_records_trust_and_filters_on_it():
    """On the textured-plane world (tests/freeviews/test_freeviews.py) every render gets
    trust scores; the photometric consistency sees the reconstruction's blur; the trust
    filter rejects by predicted PSNR and the trust ranking keeps the highest."""
    from schemas.freeview import FreeViewConfig

    from tests.freeviews.test_freeviews import _run, setup as setup_fixture

    s = setup_fixture.__wrapped__()
    res = _run(s, FreeViewConfig())
    good = [r for r in res.records if r.passed]
    assert good and all(0.5 < r.photo_support <= 1.0 for r in good)
    assert all(15.0 < r.photo_psnr < 60.0 for r in good)  # blurred render vs sharp photos
    assert all(math.isnan(r.certain_share) for r in res.records)  # no grid given
    assert all(np.isfinite(r.pred_psnr) for r in res.records)
    # trust filter with a threshold between the views' predictions
    preds = sorted(r.pred_psnr for r in res.records)
    cut = 0.5 * (preds[1] + preds[-2])
    cfg = FreeViewConfig.model_validate({"trust": {"filter": "trust", "min_psnr": cut},
                                         "pose": {"enabled": False},
                                         "final": {"rank_by": "trust", "target": 1,
                                                   "cap_to_target": True,
                                                   "trust_thresholds": [-1e9]}})
    r2 = _run(s, cfg)
    for r in r2.records:
        assert r.passed == (r.pred_psnr >= cut and r.black_ratio <= 0.2)
        assert r.passed or "trust" in r.fail_reasons or "black" in r.fail_reasons
    if r2.n_final:
        best = max((r for r in r2.records if r.passed), key=lambda r: r.pred_psnr)
        assert list(r2.final_candidates) == [best.candidate]
    with pytest.raises(ValueError, match="trust.enabled"):
        FreeViewConfig.model_validate({"trust": {"enabled": False, "filter": "trust"}})


def test_lvsm_sampler_weights_free_targets_by_trust():
    """SceneViews.view_weight (e.g. loss_weight of the stored pred_psnr) scales the loss
    weight of free-view targets only."""
    from freescale_core.downstream.lvsm.sampler import SceneViews, ViewSampler

    rng = np.random.default_rng(3)
    n_cap, n_free = 40, 60
    n = n_cap + n_free
    is_free = np.r_[np.zeros(n_cap, bool), np.ones(n_free, bool)]
    frame = np.r_[np.arange(n_cap), -np.ones(n_free, np.int64)]
    edges = (rng.integers(0, n, 600), rng.integers(0, n, 600), rng.random(600))
    vw = np.r_[np.full(n_cap, 7.0), loss_weight(rng.uniform(15, 30, n_free), 25.0)]
    scene = SceneViews("t", is_free, frame, edges, view_weight=vw)
    s = ViewSampler(graph_prob=1.0, novel_target_weight=0.3)
    seen_free = 0
    for k in range(60):
        x = s.sample(scene, np.random.default_rng(k), step=0)
        want = np.where(is_free[x.target_ids], 0.3 * vw[x.target_ids], 1.0).astype(np.float32)
        np.testing.assert_allclose(x.target_weight, want, rtol=1e-6)
        seen_free += int(is_free[x.target_ids].sum())
    assert seen_free > 0
    with pytest.raises(ValueError, match="view_weight"):
        SceneViews("t", is_free, frame, edges, view_weight=np.ones(3))


def test_photometric_consistency_ignores_masked_out_photo_pixels():
    """A 4th channel (object mask) removes support exactly where the photo is masked out,
    and what the photo shows there no longer changes the score."""
    rng = np.random.default_rng(5)
    view, refs = _flat_scene(rng)
    ph, ref = refs[0]
    H, W = ph.shape[:2]
    _, s_full, _ = photometric_consistency(view, [(ph, ref)])
    a = np.full((H, W, 1), 255, np.uint8)
    a[:, W // 2:] = 0
    p1, s1, e1 = photometric_consistency(view, [(np.concatenate([ph, a], -1), ref)])
    assert 0 < s1 < s_full
    junk = ph.copy()
    junk[:, W // 2:] = 255 - junk[:, W // 2:]
    p2, s2, e2 = photometric_consistency(view, [(np.concatenate([junk, a], -1), ref)])
    assert s2 == s1 and p2 == pytest.approx(p1)
    np.testing.assert_array_equal(np.isnan(e1), np.isnan(e2))
    full = np.concatenate([ph, np.full((H, W, 1), 255, np.uint8)], -1)
    assert photometric_consistency(view, [(full, ref)])[1] == s_full


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_view_angle_kernel_equals_the_numpy_definition_on_a_render_sized_view(seed):
    """The numba pass of view_angle_deg against the camera-by-camera numpy code it replaced
    (issue 63) at a free view's size (96x128), 36 training cameras of mixed intrinsics
    around the view (some behind it, some seeing only part), empty pixels: equal to 1e-6 deg,
    the documented tolerance (the same formulas, the projection summed in another order)."""
    rng = np.random.default_rng(seed)
    H, W = 96, 128
    alpha = (rng.random((H, W)) > 0.1).astype(np.float32)
    view = _view(rng, H, W, pose=_pose([0.1, -0.2, 0.0], 0.05), f=110.0,
                 depth=(2.0 + 3 * rng.random((H, W))).astype(np.float32), alpha=alpha)
    T = 36
    ang = rng.uniform(-math.pi, math.pi, T)
    poses = np.stack([_pose([2 * math.sin(t), rng.normal(0, 0.3), 3.0 - 3 * math.cos(t)],
                            -0.7 * t) for t in ang])
    intr = [rng.uniform(80, 140, T), rng.uniform(80, 140, T), rng.uniform(50, 70, T),
            rng.uniform(40, 55, T), np.full(T, 128.0), np.full(T, 96.0)]
    for stride in (1, 2):
        got = view_angle_deg(view, poses, *intr, stride=stride)
        want = view_angle_deg_numpy(view, poses, *intr, stride=stride)
        assert 0.0 < want < 180.0
        assert got == pytest.approx(want, abs=1e-6)
    empty = _view(rng, H, W, alpha=np.zeros((H, W), np.float32))
    assert math.isnan(view_angle_deg(empty, poses, *intr))


@pytest.mark.parametrize("seed", [0, 1])
def test_photometric_kernel_equals_the_numpy_code_on_a_render_sized_view(seed):
    """The numba pass of photometric_consistency against the numpy code it replaced (issue
    63) at a free view's size (96x128) with three references of other sizes, uint8 and float
    photos, empty and occluded pixels, points beyond the photos' borders: bit-identical
    (the same operations in the same order after numpy's projection)."""
    rng = np.random.default_rng(seed)
    H, W = 96, 128
    alpha = (rng.random((H, W)) > 0.1).astype(np.float32)
    view = _view(rng, H, W, pose=_pose([0.0, 0.0, 0.0]), f=110.0,
                 depth=(3.0 + 0.2 * rng.random((H, W))).astype(np.float32), alpha=alpha)
    refs = []
    for k, (c, yaw, (hr, wr)) in enumerate((([0.3, 0.1, 0.0], 0.05, (90, 120)),
                                            ([-0.4, 0.0, 0.2], -0.08, (96, 128)),
                                            ([0.1, -0.2, -0.1], 0.2, (70, 100)))):
        pose = _pose(c, yaw)
        # reference depth from the free view's own surface (so many pixels are supported):
        # a plane at the free view's median depth, plus an occluder patch
        dep = np.full((hr, wr), 3.1 - c[2], np.float32) * (1 + 0.01 * rng.random((hr, wr)))
        dep[10:25, 30:50] = 1.0
        ref = RenderedView(None, dep.astype(np.float32), np.ones((hr, wr), np.float32), pose,
                           100.0, 100.0, wr / 2, hr / 2)
        photo = rng.random((hr, wr, 3))
        refs.append(((photo * 255).astype(np.uint8) if k != 1 else photo.astype(np.float32),
                     ref))
    p, s, e = photometric_consistency(view, refs)
    p0, s0, e0 = photometric_consistency_numpy(view, refs)
    assert 0.2 < s < 1
    assert s == s0 and p == p0
    np.testing.assert_array_equal(e, e0)
