"""Stages 7-10 end to end on the exact textured-plane world (see test_rectify.PlaneWorld)."""

from __future__ import annotations

from dataclasses import asdict

import math

import cv2
import numpy as np
import pytest

from freescale_core.geometry.cameras import Cameras
from freescale_core.errors import ShapeError
from freescale_core.freeviews.run import final_selection, run_freeviews
from schemas.freeview import (FinalSelectConfig, FreeViewConfig, PoseRectifyConfig,
                              QualityConfig, RectifierConfig, ReferenceConfig)

from tests.freeviews.test_rectify import H, K, W, PlaneWorld, cam, psnr

BLUR = 0.8  # the "reconstruction" renders the world slightly blurred


@pytest.fixture(scope="module")
def setup():
    world = PlaneWorld()

    def truth(pose, fx, fy, cx, cy, w, h):
        return world.render(pose, fx, fy, cx, cy, w, h)

    def render_fn(pose, fx, fy, cx, cy, w, h):
        rgb, d, a = world.render(pose, fx, fy, cx, cy, w, h)
        return cv2.GaussianBlur(rgb, (0, 0), BLUR), d, a

    xs = (-1.0, -0.3, 0.3, 1.0)
    train = Cameras(np.stack([cam([x, 0.0, 0.0], target=(0.3 * x, 0.0, 4.0)) for x in xs]),
                    *K, W, H)
    photos = [(truth(train.world_from_cam[i], *K, W, H)[0] * 255).round().astype(np.uint8)
              for i in range(len(train))]
    cand_poses = [
        cam([0.3, 0.2, 0.5]),                          # 0 good
        cam([0.5, 0.0, 0.5], target=(2.0, 0.0, 4.0)),  # 1 half off the plane: rescued
        cam([0.0, 0.0, 0.2], target=(0.0, 0.0, -4.0)),  # 2 looks away: rejected
        cam([-0.6, -0.2, 0.3], target=(-0.3, 0.1, 4.0)),  # 3 good
        cam([0.9, 0.3, 0.8], target=(0.5, 0.0, 4.0)),  # 4 good (not selected)
        cam([-1.2, 0.4, 0.6], target=(-0.2, 0.2, 4.0)),  # 5 good
        cam([0.1, -0.5, 1.0]),                         # 6 good (not selected)
        cam([0.6, -0.3, 0.2], target=(0.6, -0.3, 4.0)),  # 7 good
    ]
    cands = Cameras(np.stack(cand_poses), *K, W, H)
    selected = np.array([0, 1, 2, 3, 5, 7])
    T = len(train)
    # graph: candidate j is node T + j; 5 has only a 2-hop path, 7 is isolated
    edges = (np.array([T + 0, T + 0, T + 1, T + 3, T + 5, T + 6, T + 3]),
             np.array([2, 3, 2, 1, T + 6, 0, 0]),
             np.array([0.5, 0.3, 0.2, 0.6, 0.7, 0.4, 0.2]))
    return dict(world=world, truth=truth, render_fn=render_fn, train=train, photos=photos,
                cands=cands, selected=selected, edges=edges)


def _run(s, cfg=None, **kw):
    return run_freeviews(s["train"], lambda i: s["photos"][i], s["cands"], s["selected"],
                         s["edges"], kw.pop("render_fn", s["render_fn"]),
                         cfg or FreeViewConfig(rectifier=RectifierConfig(backend="reproject")),
                         seed=0, **kw)


@pytest.fixture(scope="module")
def result(setup):
    return _run(setup)


def test_counts_add_up(result, setup):
    c = result.counts
    recs = {r.candidate: r for r in result.records}
    assert [r.candidate for r in result.records] == list(setup["selected"])
    assert c["candidates"] == 6
    assert c["passed_first"] + c["rescued"] + c["rejected"] == 6
    assert c["rendered"] == 6 + sum(r.n_rect_steps for r in result.records)
    assert c["final"] == result.n_final == len(result.rgb) == len(result.depth)
    assert c["scarce"] and result.scarce  # 5 views < target 100
    assert recs[0].passed_first and not recs[0].n_rect_steps
    assert not recs[2].passed and recs[2].n_rect_steps == 3 and math.isnan(recs[2].rect_step)
    assert "black" in recs[2].fail_reasons


def test_pose_rectification_rescues_a_view(result, setup):
    r = next(r for r in result.records if r.candidate == 1)
    assert not r.passed_first and r.passed and 1 <= r.n_rect_steps <= 3
    assert r.rect_step in (0.7, 0.5, 0.3)
    # the final pose lies on the segment from the nearest training camera (x = 0.3) to it
    ref = setup["train"].world_from_cam[2]
    c0 = setup["cands"].world_from_cam[1]
    assert np.allclose(r.world_from_cam[:3, 3],
                       ref[:3, 3] + r.rect_step * (c0[:3, 3] - ref[:3, 3]))
    assert result.counts["rescued"] >= 1


def test_every_final_view_meets_the_thresholds(result):
    q = QualityConfig()
    finals = [r for r in result.records if r.final]
    assert finals and all(r.passed for r in finals)
    for r in finals:
        assert r.brisque < q.brisque_max and r.black_ratio <= q.black_ratio_max
        assert r.depth_validity > q.depth_validity_min
    assert list(result.final_candidates) == sorted(r.candidate for r in finals)


def test_reference_rules_are_recorded(result):
    recs = {r.candidate: r for r in result.records}
    assert (recs[0].reference_view, recs[0].reference_rule) == (2, "graph_direct")
    assert (recs[5].reference_view, recs[5].reference_rule) == (0, "graph_2hop")
    assert recs[7].reference_rule == "pose_fallback"
    assert all(r.rectifier == "reproject" for r in recs.values() if r.final)


def test_graph_reference_uses_the_overlap_at_the_final_pose(setup, result):
    """With ``overlap_fn`` the graph rule asks for the WIoU of every final view at its final
    pose (the rescued view 1 was moved) and takes the best training view ('wiou_direct');
    rows with no shared voxel fall back to the stored graph; 'stored_graph' never asks."""
    calls = []
    T = len(setup["train"])

    def overlap_fn(cams):
        calls.append(cams)
        ov = np.zeros((len(cams), T))
        ov[:, 3] = 0.5
        ov[:, 1] = 0.2
        ov[0] = 0.0  # the first final view shares nothing at its final pose
        return ov

    res = _run(setup, overlap_fn=overlap_fn)
    assert len(calls) == 1 and len(calls[0]) == res.n_final
    recs = {r.candidate: r for r in res.records}
    finals = [recs[int(c)] for c in res.final_candidates]
    for k, r in enumerate(finals):
        assert np.array_equal(calls[0].world_from_cam[k], r.world_from_cam)
        assert calls[0].fx[k] == r.fx and calls[0].width[k] == r.width
    assert any(not r.passed_first for r in finals)  # a moved pose is among them
    assert (finals[0].reference_rule, finals[0].reference_view) == (
        next(x for x in result.records if x.candidate == finals[0].candidate).reference_rule,
        next(x for x in result.records if x.candidate == finals[0].candidate).reference_view)
    for r in finals[1:]:
        assert (r.reference_view, r.reference_rule, r.reference_score) == (3, "wiou_direct", 0.5)
    old = FreeViewConfig(reference=ReferenceConfig(overlap="stored_graph"),
                         rectifier=RectifierConfig(backend="reproject"))
    calls.clear()
    res_old = _run(setup, old, overlap_fn=overlap_fn)
    assert not calls
    assert [r.reference_view for r in res_old.records] == [r.reference_view
                                                            for r in result.records]
    with pytest.raises(ShapeError):
        _run(setup, overlap_fn=lambda cams: np.zeros((len(cams), T + 1)))


def test_reproject_raises_psnr_against_truth(result, setup):
    before, after = [], []
    for k, j in enumerate(result.final_candidates):
        r = next(r for r in result.records if r.candidate == j)
        true = setup["truth"](r.world_from_cam, r.fx, r.fy, r.cx, r.cy, r.width, r.height)[0]
        before.append(psnr(result.rgb_render[k] / 255.0, true))
        after.append(psnr(result.rgb[k] / 255.0, true))
    assert np.mean(after) > np.mean(before) + 1.0, (before, after)


def test_none_rectifier_keeps_the_render(setup, result):
    res = _run(setup, FreeViewConfig(rectifier=RectifierConfig(backend="none")))
    assert list(res.final_candidates) == list(result.final_candidates)
    for a, b in zip(res.rgb, res.rgb_render):
        assert np.array_equal(a, b)
    assert all(r.reference_view == -1 for r in res.records)


def test_deterministic_and_cache_independent(setup, result):
    again = _run(setup, FreeViewConfig(cache_mb=0.0,
                                       rectifier=RectifierConfig(backend="reproject")))
    assert again.counts["re_rendered"] == again.n_final
    assert len(result.records) == len(again.records)
    for ra, rb in zip(result.records, again.records):
        da, db = asdict(ra), asdict(rb)
        assert da.keys() == db.keys()
        for k in da:
            a, b = np.asarray(da[k]), np.asarray(db[k])
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), k
    for a, b in zip(result.rgb, again.rgb):
        assert np.array_equal(a, b)


def test_render_scale_and_pose_reference_rule(setup):
    cfg = FreeViewConfig(render_scale=0.5, reference=ReferenceConfig(rule="pose"),
                         rectifier=RectifierConfig(backend="reproject"),
                         pose=PoseRectifyConfig(steps=[0.5]))
    res = _run(setup, cfg)
    assert all(im.shape == (H // 2, W // 2, 3) for im in res.rgb)
    assert all(r.reference_rule == "pose" for r in res.records if r.final)
    assert all(r.n_rect_steps <= 1 for r in res.records)
    assert FreeViewConfig.fast().render_scale == 0.5


def test_unavailable_rectifier_falls_back_with_a_message(setup):
    with pytest.warns(RuntimeWarning, match="difix"):
        res = _run(setup, FreeViewConfig(rectifier=RectifierConfig(backend="difix")))
    assert res.warnings and "difix" in res.warnings[0]
    assert all(r.rectifier == "none" for r in res.records if r.final)


def test_final_selection_stepwise():
    cfg = FinalSelectConfig(target=3)
    b = np.array([0.2, 0.28, 0.33, 0.31, 0.45, 0.26])
    keep, t, scarce = final_selection(b, cfg)
    # 0.25: 1 view; 0.30: 3 views (0.2, 0.28, 0.26) -> stop
    assert t == pytest.approx(0.3) and not scarce
    assert list(np.flatnonzero(keep)) == [0, 1, 5]
    keep, t, scarce = final_selection(b, FinalSelectConfig(target=2, cap_to_target=True))
    assert t == pytest.approx(0.3) and list(np.flatnonzero(keep)) == [0, 5]
    keep, t, scarce = final_selection(b, FinalSelectConfig(target=10))
    assert keep.all() and math.isnan(t) and scarce
    keep, t, scarce = final_selection(np.array([]), FinalSelectConfig(target=1))
    assert keep.size == 0 and scarce


def test_bad_inputs_are_rejected(setup):
    with pytest.raises(ValueError, match="duplicates"):
        run_freeviews(setup["train"], lambda i: setup["photos"][i], setup["cands"],
                      np.array([0, 0]), None, setup["render_fn"])
    with pytest.raises(ValueError, match="lie in"):
        run_freeviews(setup["train"], lambda i: setup["photos"][i], setup["cands"],
                      np.array([99]), None, setup["render_fn"])
    with pytest.raises(ValueError, match="non-decreasing"):
        FreeViewConfig(final=FinalSelectConfig(thresholds=[0.5, 0.3]))


def test_object_masks_raise_the_black_limit_and_keep_empty_views_out(setup, result):
    """With object masks (half of each training photo is background) a view half off the
    object is no longer 'black' at its own pose; a view of nothing is still rejected."""
    m = np.zeros((H, W), bool)
    m[:, : W // 2] = True
    res = _run(setup, train_masks=lambda i: m)
    before = {r.candidate: r for r in result.records}
    after = {r.candidate: r for r in res.records}
    assert not before[1].passed_first and "black" in before[1].fail_reasons
    assert after[1].passed_first and after[1].black_ratio > 0.2
    assert not after[2].passed and "black" in after[2].fail_reasons


def _records_equal(ra, rb):
    da, db = asdict(ra), asdict(rb)
    assert da.keys() == db.keys()
    for k in da:
        a, b = np.asarray(da[k]), np.asarray(db[k])
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), k


def test_batched_render_path_gives_the_same_table(setup, result):
    """A render function with a ``.batch`` attribute is called once per batch (first poses,
    each pose-rectification step) and the table and images equal the view-by-view run."""
    calls = []

    def render_fn(*a):
        return setup["render_fn"](*a)

    def batch(poses, fx, fy, cx, cy, w, h):
        calls.append(len(poses))
        return [setup["render_fn"](poses[i], fx[i], fy[i], cx[i], cy[i], int(w[i]), int(h[i]))
                for i in range(len(poses))]

    render_fn.batch = batch
    got = _run(setup, render_fn=render_fn)
    assert calls and calls[0] == len(setup["selected"])
    assert got.counts == result.counts
    for ra, rb in zip(result.records, got.records):
        _records_equal(ra, rb)
    for a, b in zip(result.rgb, got.rgb):
        assert np.array_equal(a, b)
    assert set(got.timings) >= {"render", "render_rectify", "scores", "brisque", "rectify"}


def test_reserve_is_drawn_only_while_short_of_the_target(setup, result):
    """Reserve candidates are rendered after the selected ones while fewer than the target
    passed: with the target met by the selection none is drawn; short of it, the next batch
    is, and its records follow the selected ones."""
    base = FreeViewConfig(rectifier=RectifierConfig(backend="reproject"))
    n_pass = result.counts["passed"]
    met = base.model_copy(update={"final": FinalSelectConfig(target=n_pass)})
    r1 = _run(setup, met, reserve=np.array([4, 6]))
    assert r1.counts["reserve_drawn"] == 0 and len(r1.records) == len(setup["selected"])
    short = base.model_copy(update={"final": FinalSelectConfig(target=n_pass + 1)})
    r2 = _run(setup, short, reserve=np.array([4, 6]))
    assert r2.counts["reserve_drawn"] == 2
    assert [r.candidate for r in r2.records][-2:] == [4, 6]
    assert r2.counts["passed"] > n_pass and r2.counts["candidates"] == len(setup["selected"]) + 2
    for ra, rb in zip(result.records, r2.records):  # the selected views are unchanged
        _records_equal(ra, rb)
    with pytest.raises(ValueError, match="reserve"):
        _run(setup, short, reserve=np.array([0]))  # already selected
