"""Stage 10 reference choice at the final pose: ``TrainOverlap`` (direct WIoU from the
certainty grid, optionally with a view-direction kernel) and its use by the graph rule."""

from __future__ import annotations

import numpy as np
import pytest

from freescale_core.geometry.cameras import Cameras, look_at
from freescale_core.select.certainty import CertaintyGrid
from freescale_core.freeviews.references import TrainOverlap, ViewGraph, select_reference
from freescale_core.select.view_graph import wiou_matrix
from freescale_core.select.visibility import compute_visibility
from schemas.freeview import ReferenceConfig
from schemas.select import VisibilityConfig

UP = np.array([0.0, 0.0, 1.0])
W, H, F = 64, 48, 50.0


def _cams(eyes, targets):
    poses = np.stack([look_at(np.asarray(e, float), np.asarray(t, float), UP)
                      for e, t in zip(eyes, targets)])
    return Cameras(poses, F, F, W / 2, H / 2, W, H)


@pytest.fixture(scope="module")
def grid():
    rng = np.random.default_rng(0)
    R = 12
    vals = np.zeros((R, R, R), np.float32)
    vals[3:9, 3:9, 3:9] = rng.uniform(0.1, 1.0, (6, 6, 6))  # a block of certain voxels
    return CertaintyGrid(vals, [-1.0, -1, -1], [1.0, 1, 1])


@pytest.mark.parametrize("mode", ["frustum", "occlusion"])
def test_direct_overlap_equals_the_wiou_matrix(grid, mode):
    """Without the angle kernel, a row of TrainOverlap is the WIoU matrix entry (Eq. 3) of the
    complete graph over training + query cameras."""
    rng = np.random.default_rng(1)
    eyes = rng.normal(size=(7, 3)) * 3.0
    targets = rng.normal(size=(7, 3)) * 0.3
    train, query = _cams(eyes[:5], targets[:5]), _cams(eyes[5:], targets[5:])
    vc = VisibilityConfig(mode=mode)
    ov = TrainOverlap(grid, train, vc)(query)
    allc = Cameras.concat([train, query])
    Wm = wiou_matrix(compute_visibility(allc, grid, vc), np.arange(7), np.float64)
    assert ov.shape == (2, 5)
    np.testing.assert_allclose(ov, Wm[5:, :5], atol=1e-12)
    assert (ov > 0).any()


def test_angle_kernel_prefers_the_same_side(grid):
    """Two training cameras see all voxels (same plain WIoU), one from the query's side and
    one from the opposite side: the direction-aware WIoU keeps the first, drops the second."""
    train = _cams([[0.0, -6.0, 0.5], [0.0, 6.0, 0.5]], [[0, 0, 0], [0, 0, 0]])
    query = _cams([[0.8, -6.0, 0.3]], [[0, 0, 0]])
    plain = TrainOverlap(grid, train)(query)[0]
    assert plain[0] == pytest.approx(plain[1])  # frustum visibility cannot tell them apart
    d = TrainOverlap(grid, train, angle_deg=(5.0, 30.0))(query)[0]
    assert d[0] > 0.5 and d[1] == 0.0
    assert d[0] <= plain[0] + 1e-12
    # a kernel that accepts every angle is Eq. 3
    np.testing.assert_allclose(TrainOverlap(grid, train, angle_deg=(180.0, 180.0))(query)[0],
                               plain, atol=1e-12)
    with pytest.raises(ValueError):
        TrainOverlap(grid, train, angle_deg=(30.0, 5.0))
    assert TrainOverlap(grid, train)(Cameras(np.zeros((0, 4, 4)), F, F, 1, 1, W, H)).shape \
        == (0, 2)


def test_angle_kernel_matches_its_definition(grid):
    rng = np.random.default_rng(2)
    eyes = rng.normal(size=(9, 3)) * 3.0
    train, query = _cams(eyes[:6], np.zeros((6, 3))), _cams(eyes[6:], np.zeros((3, 3)))
    got = TrainOverlap(grid, train, angle_deg=(10.0, 50.0), chunk=4)(query)
    allc = Cameras.concat([train, query])
    vis = compute_visibility(allc, grid, cells_per_axis=0)
    M, C, X = vis.dense(), vis.weights, grid.nonzero()[1]
    want = np.zeros((3, 6))
    for i in range(3):
        for t in range(6):
            a = X - allc.centers[6 + i]
            b = X - allc.centers[t]
            cos = (a * b).sum(1) / np.linalg.norm(a, axis=1) / np.linalg.norm(b, axis=1)
            ang = np.degrees(np.arccos(np.clip(cos, -1, 1)))
            kap = np.clip((50.0 - ang) / 40.0, 0.0, 1.0)
            inter = (C * M[6 + i] * M[t] * kap).sum()
            den = (C * M[6 + i]).sum() + (C * M[t]).sum() - inter
            want[i, t] = inter / den if den > 0 else 0.0
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert 0 < got.max() < 1


def test_graph_rule_uses_the_final_pose_overlap():
    train = np.stack([look_at(np.array([x, -5.0, 0.0]), np.zeros(3), UP) for x in (-2, 0, 2)])
    free = look_at(np.array([1.9, -5.0, 0.0]), np.zeros(3), UP)
    g = ViewGraph.from_edges(3, 5, [3], [0], [0.9])  # stored edge of the original pose: 0
    cfg = ReferenceConfig(rule="graph")
    c = select_reference(cfg, train, free, g, 3, overlap=np.array([0.1, 0.3, 0.6]))
    assert (c.train_index, c.rule, c.score) == (2, "wiou_direct", 0.6)
    # ties go to the lowest index
    c = select_reference(cfg, train, free, g, 3, overlap=np.array([0.1, 0.6, 0.6]))
    assert c.train_index == 1
    # no shared certain voxel at the final pose: the stored graph, labelled as such
    c = select_reference(cfg, train, free, g, 3, overlap=np.zeros(3))
    assert (c.train_index, c.rule) == (0, "graph_direct")
    c = select_reference(cfg, train, free, None, None, overlap=np.zeros(3))
    assert (c.train_index, c.rule) == (2, "pose_fallback")
    # the earlier behaviour stays selectable and ignores the overlap row
    old = ReferenceConfig(rule="graph", overlap="stored_graph")
    c = select_reference(old, train, free, g, 3, overlap=np.array([0.1, 0.3, 0.6]))
    assert (c.train_index, c.rule) == (0, "graph_direct")
    # the pose rule ignores it too
    c = select_reference(ReferenceConfig(rule="pose"), train, free, g, 3,
                         overlap=np.array([0.9, 0.0, 0.0]))
    assert (c.train_index, c.rule) == (2, "pose")
    with pytest.raises(Exception):
        select_reference(cfg, train, free, g, 3, overlap=np.ones(4))


def test_reference_config_angles_validated():
    assert ReferenceConfig().overlap_angle_deg == (5.0, 30.0)
    assert ReferenceConfig(overlap_angle_deg=None).overlap_angle_deg is None
    with pytest.raises(Exception):
        ReferenceConfig(overlap_angle_deg=(40.0, 10.0))


def test_pipeline_overlap_fn_follows_the_config(grid):
    from types import SimpleNamespace

    from freescale_core.freeviews.run import make_overlap_fn
    from schemas.freeview import FreeViewConfig
    from schemas.select import SelectConfig

    train = _cams([[0.0, -6.0, 0.5], [0.0, 6.0, 0.5]], [[0, 0, 0], [0, 0, 0]])
    sc = SelectConfig().model_dump(mode="json")
    sc["visibility"]["mode"] = "occlusion"
    sel = SimpleNamespace(grid=grid, config=sc)
    fn = make_overlap_fn(sel, train, FreeViewConfig())
    assert isinstance(fn, TrainOverlap)
    assert fn.visibility.mode == "occlusion" and fn.angle_deg == (5.0, 30.0)
    forced = FreeViewConfig(reference=ReferenceConfig(visibility="frustum",
                                                      overlap_angle_deg=None))
    fn = make_overlap_fn(sel, train, forced)
    assert fn.visibility.mode == "frustum" and fn.angle_deg is None
    assert make_overlap_fn(sel, train, FreeViewConfig(reference=ReferenceConfig(rule="pose"))) \
        is None
    stored = FreeViewConfig(reference=ReferenceConfig(overlap="stored_graph"))
    assert make_overlap_fn(sel, train, stored) is None
    assert make_overlap_fn(SimpleNamespace(grid=None, config=sc), train, FreeViewConfig()) \
        is None
