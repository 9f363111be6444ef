"""The selection core end to end (METHOD.md stages 2-6), feasibility, pictures, a real scene."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.geometry.cameras import Cameras, colmap_to_cam_from_world, invert_pose, look_at
from freescale_core.select.certainty import CertaintyGrid
from freescale_core.errors import DegenerateSceneError
from freescale_core.select.feasibility import check_feasibility
from freescale_core.scene.gaussians import Gaussians
from freescale_core.select.run import SelectionResult, run_selection
from freescale_core.select.view_graph import wiou_matrix
from freescale_core.select.visibility import compute_visibility
from schemas.select import FeasibilityConfig, SelectConfig
from tests.conftest import real_scene_dir

DISPOSITIONS = {"train", "infeasible", "suppressed", "free_view"}


def _room(n: int = 30_000, n_cams: int = 24, seed: int = 0):
    """Gaussians on the walls/floor of a 6 x 4 x 3 room and on a table; a camera walk."""
    rng = np.random.default_rng(seed)
    k = n // 6
    walls = [np.c_[rng.uniform(-3, 3, k), np.full(k, -2), rng.uniform(0, 3, k)],
             np.c_[rng.uniform(-3, 3, k), np.full(k, 2), rng.uniform(0, 3, k)],
             np.c_[np.full(k, -3), rng.uniform(-2, 2, k), rng.uniform(0, 3, k)],
             np.c_[np.full(k, 3), rng.uniform(-2, 2, k), rng.uniform(0, 3, k)],
             np.c_[rng.uniform(-3, 3, k), rng.uniform(-2, 2, k), np.zeros(k)],
             np.c_[rng.uniform(-0.6, 0.6, n - 5 * k), rng.uniform(-0.4, 0.4, n - 5 * k),
                   np.full(n - 5 * k, 0.8)]]
    pts = np.concatenate(walls) + rng.normal(0, 0.003, (n, 3))
    g = Gaussians(pts, rng.normal(np.log(0.01), 0.3, (n, 3)), np.tile([1, 0, 0, 0], (n, 1)),
                  rng.normal(2, 1, n), np.zeros((n, 1, 3)))
    t = np.linspace(0, 2 * np.pi, n_cams, endpoint=False)
    eye = np.c_[1.8 * np.cos(t), 1.2 * np.sin(t), np.full(n_cams, 1.5)]
    tgt = np.c_[0.5 * np.cos(t + 2), 0.5 * np.sin(t + 2), np.full(n_cams, 0.8)]
    cams = Cameras(look_at(eye, tgt, [0, 0, 1]), 200.0, 200.0, 160.0, 120.0, 320, 240)
    return g, cams


@pytest.fixture(scope="module")
def room():
    return _room()


@pytest.fixture(scope="module")
def room_result(room):
    g, cams = room
    return run_selection(g, cams, SelectConfig.fast(), seed=3, scene_id="room")


def test_result_is_consistent(room, room_result):
    g, cams = room
    r = room_result
    T, Nc = len(cams), len(r.candidates)
    assert r.n_views == T + Nc == len(r.disposition) == len(r.score)
    assert set(np.unique(r.disposition)) <= DISPOSITIONS
    assert np.all(r.disposition[:T] == "train")
    assert Nc == len(r.modes) == len(r.traj_id) == len(r.frame_idx) == len(r.infeasible_reason)
    infeas = r.disposition[T:] == "infeasible"
    np.testing.assert_array_equal(infeas, r.infeasible_reason != "")
    assert np.all(np.isnan(r.score[T:][infeas])) and np.all(np.isfinite(r.score[T:][~infeas]))
    c = r.counts
    assert c["n_candidates"] == Nc
    assert c["n_infeasible_outside_box"] + c["n_infeasible_inside_structure"] == infeas.sum()
    assert c["n_selected"] == np.sum(r.disposition == "free_view") == len(r.selected)
    assert (c["n_suppressed_overlap"] + c["n_suppressed_budget"] + c["n_zero_score"]
            == np.sum(r.disposition == "suppressed"))
    assert 0 < c["n_selected"] <= SelectConfig.fast().nms.max_views
    np.testing.assert_array_equal(np.sort(r.selected), np.flatnonzero(r.disposition == "free_view"))
    # edges only among kept views, src < dst, WIoU in (threshold, 1]
    kept = set(range(T)) | set(r.selected.tolist())
    assert len(r.edges) > 0 and np.all(r.edges.src < r.edges.dst)
    assert set(r.edges.src.tolist()) | set(r.edges.dst.tolist()) <= kept
    assert np.all((r.edges.wiou > 0.01) & (r.edges.wiou <= 1))
    assert set(r.timings) >= {"grid", "candidates", "feasibility", "visibility", "nms", "graph",
                              "total"}
    assert r.grid.R == 48 and 32 <= r.R_adaptive <= 256 and r.R_adaptive_reason


def test_kept_views_satisfy_the_nms_rule(room, room_result):
    """Every pair of kept free views, and free view vs training view, has WIoU < 0.7;
    every overlap-suppressed candidate has a kept view at or above 0.7 (exact WIoU)."""
    g, cams = room
    r = room_result
    T = len(cams)
    allc = Cameras.concat([cams, r.candidates])
    feas = np.r_[np.arange(T), T + np.flatnonzero(r.infeasible_reason == "")]
    cfg = SelectConfig.fast()
    vis = compute_visibility(allc.subset(feas), r.grid, cfg.visibility)
    W = wiou_matrix(vis, np.arange(len(feas)), np.float64)
    pos = {int(n): i for i, n in enumerate(feas)}
    sel = np.array([pos[int(s)] for s in r.selected])
    kept = np.r_[np.arange(T), sel]
    Wss = W[np.ix_(sel, kept)]
    Wss[np.arange(len(sel)), T + np.arange(len(sel))] = 0
    assert Wss.max() < 0.7
    sup = [pos[int(n)] for n in np.flatnonzero(r.suppress_reason == "overlap")]
    assert len(sup) > 0 and np.all(W[np.ix_(sup, kept)].max(axis=1) >= 0.7)


def test_same_seed_same_result(room, room_result):
    g, cams = room
    again = run_selection(g, cams, SelectConfig.fast(), seed=3, scene_id="room")
    np.testing.assert_array_equal(again.selected, room_result.selected)
    np.testing.assert_array_equal(again.disposition, room_result.disposition)
    np.testing.assert_array_equal(again.candidates.world_from_cam,
                                  room_result.candidates.world_from_cam)
    np.testing.assert_array_equal(again.edges.src, room_result.edges.src)
    other = run_selection(g, cams, SelectConfig.fast(), seed=4)
    assert not np.array_equal(other.candidates.world_from_cam,
                              room_result.candidates.world_from_cam)


@pytest.mark.parametrize("mode", ["pose_distance", "none"])
def test_ablation_modes(room, mode):
    g, cams = room
    cfg = SelectConfig.fast()
    cfg.graph.mode = mode
    r = run_selection(g, cams, cfg, seed=1)
    assert set(np.unique(r.disposition)) <= DISPOSITIONS
    assert 0 < r.counts["n_selected"] <= cfg.nms.max_views
    if mode == "none":
        assert len(r.edges) == 0
        ok = np.isfinite(r.score[r.n_train:])
        top = np.sort(r.score[r.n_train:][ok])[::-1][:r.counts["n_selected"]]
        np.testing.assert_allclose(np.sort(r.score[r.selected])[::-1], top)
    else:
        assert np.all(np.isnan(r.score)) and np.all(np.isnan(r.edges.wiou))
        assert np.all(r.edges.distance < cfg.nms.pose_threshold)


def test_occlusion_visibility_runs(room):
    g, cams = room
    cfg = SelectConfig.fast()
    cfg.visibility.mode = "occlusion"
    r = run_selection(g, cams, cfg, seed=1)
    assert r.counts["n_selected"] > 0


def test_training_camera_outside_box_or_blind(room):
    g, cams = room
    out = Cameras(look_at([[40.0, 40, 40]], [[80.0, 80, 80]], [0, 0, 1]), 200.0, 200.0, 160.0,
                  120.0, 320, 240)  # far outside the box, looking away: sees no voxel
    allc = Cameras.concat([out, cams])
    r = run_selection(g, allc, SelectConfig.fast(), seed=0)
    assert r.score[0] == 0 and r.disposition[0] == "train"
    assert np.isnan(r.wiou_to_train[0]) or r.wiou_to_train[0] == 0
    assert r.counts["n_selected"] > 0


def test_degenerate_inputs_raise_scene_errors(room):
    g, cams = room
    bad = Gaussians(g.means.copy(), g.log_scales, g.quats_wxyz, g.opacity_logits, g.sh)
    bad.means[5] = np.nan
    with pytest.raises(DegenerateSceneError, match="'x1'"):
        run_selection(bad, cams, SelectConfig.fast(), scene_id="x1")
    with pytest.raises(DegenerateSceneError):
        run_selection(g, cams.subset(np.zeros(0, int)), SelectConfig.fast())


def test_feasibility_axes_with_an_asymmetric_grid():
    R = 8
    vals = np.zeros((R, R, R), np.float32)
    vals[5, 1, 2] = 1.0  # structure only at (ix, iy, iz) = (5, 1, 2)
    grid = CertaintyGrid(vals, [0.0, 0, 0], [8.0, 16, 24])  # non-cubic voxels too
    inside = grid.voxel_centers([[5, 1, 2]])
    swapped = grid.voxel_centers([[2, 1, 5]])  # x/z swapped, as the authors' code sampled
    outside = np.array([[-1.0, 5, 5], [4, 17, 5], [4, 5, 24.5]])
    f = check_feasibility(np.concatenate([inside, swapped, outside]), grid,
                          FeasibilityConfig(occupancy_quantile=0.0))
    assert f.reason.tolist() == ["inside_structure", "", "outside_box", "outside_box",
                                 "outside_box"]
    assert f.counts == {"n_feasible": 1, "n_infeasible_outside_box": 3,
                        "n_infeasible_inside_structure": 1}
    near = grid.voxel_centers([[6, 2, 3]])  # diagonal neighbour
    assert check_feasibility(near, grid, FeasibilityConfig(occupancy_quantile=0.0)).feasible[0]
    assert not check_feasibility(near, grid, FeasibilityConfig(occupancy_quantile=0.0,
                                                               neighbourhood=1)).feasible[0]


def test_pictures_pickle_and_tables(room, room_result, tmp_path):
    import cv2

    from freescale_core.store.pictures import save_selection_plots

    g, cams = room
    paths = save_selection_plots(room_result, cams, tmp_path)
    assert [p.name for p in paths] == ["cameras.png", "certainty_maxproj.png"]
    for p in paths:
        img = cv2.imread(str(p))
        assert img is not None and img.shape[0] > 100 and img.std() > 1
    back = pickle.loads(pickle.dumps(room_result))
    assert isinstance(back, SelectionResult)
    np.testing.assert_array_equal(back.grid.values, room_result.grid.values)
    sel = room_result.selected_cameras()
    assert len(sel) == room_result.counts["n_selected"]


# ---------------------------------------------------------------------- a real scene
def _colmap_points_scene(name: str):
    pycolmap = pytest.importorskip("pycolmap")
    root = real_scene_dir(name)
    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    ids = sorted(rec.images, key=lambda i: rec.images[i].name)
    T, fx, fy, cx, cy, W, H = [], [], [], [], [], [], []
    for i in ids:
        im, cam = rec.images[i], rec.cameras[rec.images[i].camera_id]
        r = im.cam_from_world()
        q = np.asarray(r.rotation.quat)
        cfw = colmap_to_cam_from_world(np.r_[q[3], q[:3]], np.asarray(r.translation))
        T.append(invert_pose(cfw))
        K = cam.calibration_matrix()
        fx.append(K[0, 0]), fy.append(K[1, 1]), cx.append(K[0, 2]), cy.append(K[1, 2])
        W.append(cam.width), H.append(cam.height)
    pts = np.array([p.xyz for p in rec.points3D.values()])
    rgb = np.array([p.color for p in rec.points3D.values()]) / 255.0
    return Gaussians.from_points(pts, rgb), Cameras(np.stack(T), fx, fy, cx, cy, W, H)


def test_golden_fountain_points_as_gaussians():
    g, cams = _colmap_points_scene("strecha_fountain-P11")
    assert len(cams) == 11 and len(g) == 7524
    a = run_selection(g, cams, SelectConfig(), seed=0, scene_id="fountain")
    b = run_selection(g, cams, SelectConfig(), seed=0, scene_id="fountain")
    c = a.counts
    # deterministic stages: exact golden numbers; NMS: reproducible and sane
    assert c["n_candidates"] == 2000 and c["R"] == 128
    assert c["n_infeasible_outside_box"] + c["n_infeasible_inside_structure"] \
        + c["n_feasible"] == 2000
    assert 200 < c["n_feasible"] < 2000 and c["lookat_pool_size"] > 0
    assert 20 <= c["n_selected"] <= 500
    assert c == b.counts
    np.testing.assert_array_equal(a.selected, b.selected)
    # the certainty-drawn look-at points lie on the facade (where the points are)
    oc = np.isfinite(a.lookat[:, 0])
    assert np.all(a.grid.lookup(a.lookat[oc]) > 0)


def test_capture_region_counts_as_inside_box():
    """Object-centric capture: cameras outside the Gaussians' box are still feasible."""
    from freescale_core.select.certainty import CertaintyGrid
    from freescale_core.select.feasibility import check_feasibility
    from schemas.select import FeasibilityConfig

    grid = CertaintyGrid(np.zeros((8, 8, 8), np.float32), np.zeros(3), np.ones(3))
    train = np.array([[3.0, 0.5, 0.5], [4.0, 0.5, 0.5]])
    cand = np.array([[3.5, 0.5, 0.5], [9.0, 0.5, 0.5], [0.5, 0.5, 0.5]])
    on = check_feasibility(cand, grid, FeasibilityConfig(), train_centers=train)
    off = check_feasibility(cand, grid, FeasibilityConfig(include_cameras=False), train_centers=train)
    assert on.reason.tolist() == ["", "outside_box", ""]
    assert off.reason.tolist() == ["outside_box", "outside_box", ""]


def test_robust_box_ignores_far_floaters():
    from freescale_core.select.certainty import scene_box

    rng = np.random.default_rng(0)
    m = np.concatenate([rng.uniform(0, 1, (2000, 3)), [[500.0, 500.0, 500.0]]])
    lo, hi = scene_box(m, 0.1, 0.01, quantile=0.005)
    assert np.all(hi < 2.0)
    lo0, hi0 = scene_box(m, 0.1, 0.01, quantile=0.0)
    assert np.all(hi0 > 500.0)


def test_mass_trimmed_box_ignores_a_background_shell():
    """A quarter of the Gaussians on a far shell (big, faint: the sky of a long training run)
    defeats the quantile box; trimming the least certain 0.1% of the mass keeps the objects'
    box, and with mass_trim = 0 the shell still blows it up (so the test can fail)."""
    from freescale_core.select.certainty import _mass_trim_keep, scene_box

    rng = np.random.default_rng(1)
    obj = rng.uniform(-1, 1, (3000, 3))
    d = rng.normal(size=(1000, 3))
    shell = 30.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    m = np.concatenate([obj, shell])
    w = np.concatenate([rng.uniform(1.0, 10.0, 3000), rng.uniform(0.0, 1e-4, 1000)])
    lo, hi = scene_box(m, 0.1, 0.01, quantile=0.005, weights=w, mass_trim=0.001)
    assert np.all(hi < 1.5) and np.all(lo > -1.5)
    lo0, hi0 = scene_box(m, 0.1, 0.01, quantile=0.005, weights=w, mass_trim=0.0)
    assert np.all(hi0 > 20.0) and np.all(lo0 < -20.0)
    # the trim never drops more than half, and drops exactly the least-weight entries
    keep = _mass_trim_keep(w, 0.4)
    assert keep.sum() >= len(w) // 2
    assert w[~keep].max() <= w[keep].min()
    assert w[~keep].sum() <= 0.4 * w.sum()


def test_grid_box_uses_the_mass_trim():
    from freescale_core.scene.gaussians import Gaussians

    rng = np.random.default_rng(2)
    n_obj, n_sky = 2000, 700
    d = rng.normal(size=(n_sky, 3))
    means = np.concatenate([rng.uniform(-1, 1, (n_obj, 3)),
                            40.0 * d / np.linalg.norm(d, axis=1, keepdims=True)])
    log_scales = np.concatenate([np.full((n_obj, 3), np.log(0.02)), np.full((n_sky, 3), 1.0)])
    n = n_obj + n_sky
    g = Gaussians(means=means.astype(np.float32), log_scales=log_scales.astype(np.float32),
                  quats_wxyz=np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                  opacity_logits=np.zeros(n, np.float32), sh=np.zeros((n, 1, 3), np.float32))
    from freescale_core.select.certainty import build_certainty_grid
    from schemas.select import GridConfig

    grid, _, _ = build_certainty_grid(g, GridConfig(resolution=32))
    assert np.all(grid.bbox_max < 1.5) and np.all(grid.bbox_min > -1.5)
    wide, _, _ = build_certainty_grid(g, GridConfig(resolution=32, box_mass_trim=0.0))
    assert np.all(wide.bbox_max > 30.0)


def _mass_trim_keep_reference(w: np.ndarray, mass_trim: float) -> np.ndarray:
    """Obvious version: stable argsort, drop the prefix holding mass_trim of the total."""
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    keep = np.ones(len(w), dtype=bool)
    if w.sum() <= 0:
        return keep
    o = np.argsort(w, kind="stable")
    n = int(np.searchsorted(np.cumsum(w[o]), mass_trim * w.sum(), side="right"))
    keep[o[:min(n, len(w) // 2)]] = False
    return keep


@settings(max_examples=200, deadline=None)
@given(w=st.lists(st.sampled_from([0.0, 0.5, 1.0, 2.0, 3.0, 1e-9, 1e3]), min_size=1,
                  max_size=60),
       mass_trim=st.floats(0.0, 0.49))
def test_mass_trim_equals_the_argsort_reference(w, mass_trim):
    from freescale_core.select.certainty import _mass_trim_keep

    w = np.asarray(w)
    np.testing.assert_array_equal(_mass_trim_keep(w, mass_trim),
                                  _mass_trim_keep_reference(w, mass_trim))


def test_default_reserve_reaches_every_overlap_suppressed_candidate(room, room_result):
    """Issue 63: NMS at 0.7 and a reserve at 0.8 / 0.9 gave fewer than 100 candidates on
    scenes with hundreds of feasible ones (kermit 42 + 73 of 1,145). The default reserve ends
    at WIoU 1.0, so it holds every overlap-suppressed candidate that is not an exact
    duplicate (up to reserve_max), and starts with the 0.8 / 0.9 reserve in the same order."""
    r = room_result
    sup = np.flatnonzero(r.suppress_reason == "overlap")
    assert len(r.reserve) == len(sup) > 100
    assert set(r.reserve.tolist()) == set(sup.tolist())
    cfg = SelectConfig.fast()
    old = cfg.model_copy(update={"nms": cfg.nms.model_copy(
        update={"reserve_thresholds": [0.8, 0.9]})})
    g, cams = room
    before = run_selection(g, cams, old, seed=3, scene_id="room").reserve
    assert 0 < len(before) < len(r.reserve)
    np.testing.assert_array_equal(r.reserve[:len(before)], before)
