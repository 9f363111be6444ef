"""Sparse points' tracks: which points the training views alone could have triangulated.

A held-out evaluation must not start from points placed (and coloured) with a held-out view;
:meth:`Scene.points_seen_by` tells them apart and the trainer keeps only the others
(``ReconConfig.init_points="train"``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.geometry.cameras import Cameras
from freescale_core.scene.scene import Scene
from tests.conftest import real_scene_dir


def _scene(n_views: int, tracks: list[list[int]] | None) -> Scene:
    """A scene of ``n_views`` cameras (no images needed) and one point per track."""
    eye = np.tile(np.eye(4), (n_views, 1, 1))
    cams = Cameras(eye, np.full(n_views, 50.0), np.full(n_views, 50.0), np.full(n_views, 32.0),
                   np.full(n_views, 24.0), np.full(n_views, 64), np.full(n_views, 48))
    n_pts = 0 if tracks is None else len(tracks)
    pt = None
    if tracks is not None:
        lens = [len(t) for t in tracks]
        pt = (np.concatenate([[0], np.cumsum(lens)]).astype(np.int64),
              np.asarray([v for t in tracks for v in t], np.int64))
    return Scene("s", Path("."), [Path(f"{i}.png") for i in range(n_views)],
                 [f"{i}.png" for i in range(n_views)], cams, np.zeros((n_pts, 3)),
                 np.zeros((n_pts, 3), np.uint8), "colmap", ["PINHOLE"] * n_views,
                 points_tracks=pt)


def _obvious(tracks, idx, min_views):
    """The rule as written: a point stays when at least min(min_views, its track length) of
    its track's views are in ``idx`` (an empty track: kept)."""
    s = set(int(i) for i in idx)
    return np.array([len(t) == 0 or sum(v in s for v in t) >= min(min_views, len(t))
                     for t in tracks], bool)


tracks_st = st.integers(2, 9).flatmap(lambda n: st.tuples(
    st.just(n),
    st.lists(st.lists(st.integers(-1, n - 1), max_size=5), max_size=30),
    st.lists(st.integers(0, n - 1), unique=True, max_size=n),
    st.integers(1, 3)))


@settings(max_examples=200, deadline=None)
@given(tracks_st)
def test_points_seen_by_matches_the_obvious_rule(case):
    n, tracks, idx, k = case
    scene = _scene(n, tracks)
    got = scene.points_seen_by(np.asarray(idx, np.int64), k)
    np.testing.assert_array_equal(got, _obvious(tracks, idx, k))
    # a subset re-indexes the tracks: its own views alone give the same points
    sub = scene.subset(np.asarray(idx, np.int64))
    if len(idx):
        np.testing.assert_array_equal(sub.points_seen_by(np.arange(len(idx)), k), got)


def test_no_tracks_means_no_answer_and_bad_tracks_are_refused():
    assert _scene(3, None).points_seen_by([0, 1]) is None
    with pytest.raises(ValueError, match="tracks of 1 points"):
        s = _scene(3, [[0, 1], [1, 2]])
        Scene("s", Path("."), s.image_paths, s.image_names, s.cameras, np.zeros((2, 3)),
              np.zeros((2, 3), np.uint8), "colmap", s.camera_models,
              points_tracks=(np.array([0, 2]), np.array([0, 1])))


def test_real_scene_tracks_and_the_trainers_points():
    """strecha_fountain-P11: its points are two-view triangulations; on the every-8th split
    (views 0 and 8 held out) 2578 of 7524 use a held-out view, and the trainer starts from the
    other 4946 (``init_points="all"``: every point)."""
    from freescale_core.recon.trainer import sparse_points_for
    from freescale_core.scene.io import load_scene
    from schemas.recon import ReconConfig

    scene = load_scene(real_scene_dir("strecha_fountain-P11"))
    ptr, views = scene.points_tracks
    assert len(ptr) == len(scene.points_xyz) + 1 == 7525
    assert set(np.diff(ptr).tolist()) == {2} and views.min() >= 0
    train, test = scene.split("every8")
    assert test.tolist() == [0, 8]
    keep = scene.points_seen_by(train)
    pairs = views.reshape(-1, 2)
    np.testing.assert_array_equal(keep, ~np.isin(pairs, test).any(1))
    assert int(keep.sum()) == 4946
    xyz, rgb, why = sparse_points_for(scene, ReconConfig(), train)
    np.testing.assert_array_equal(xyz, scene.points_xyz[keep])
    np.testing.assert_array_equal(rgb, scene.points_rgb[keep])
    assert "4946 of 7524" in why
    xyz, _, why = sparse_points_for(scene, ReconConfig(init_points="all"), train)
    assert len(xyz) == 7524 and "init_points=all" in why
    # the held-out scene's own generation view: a subset keeps the points, re-indexed
    gen, held = scene.views_for("every8")
    assert int(gen.points_seen_by(np.arange(len(gen))).sum()) == 4946
