"""The published layout: the view graph keeps the weights it was built with."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from freescale_core.select.run import run_selection
from freescale_core.store.layout import write_scene_outputs
from schemas.select import SelectConfig
from tests.select.test_select import _room
from tests.store.test_figures import fake_scene


@pytest.mark.parametrize("mode", ["wiou", "pose_distance"])
def test_published_graph_has_its_weights(tmp_path, mode):
    g, cams = _room(n=6000, n_cams=12)
    cfg = SelectConfig.fast()
    cfg.graph.mode = mode
    sel = run_selection(g, cams, cfg, seed=1)
    scene = fake_scene(cams, tmp_path / "_inputs")
    write_scene_outputs(tmp_path, scene, sel, None, tmp_path / "none.ply")
    t = pq.read_table(tmp_path / "view_graph.parquet").to_pydict()
    assert len(t["src"]) == len(sel.edges) > 0
    w, d = np.asarray(t["wiou"], float), np.asarray(t["distance"], float)
    if mode == "wiou":
        assert np.all(np.isfinite(w)) and np.all((w >= 0) & (w <= 1))
    else:  # the ablation's weight is its pose distance (was dropped: all NaN)
        assert np.all(np.isfinite(d))
        np.testing.assert_allclose(d, sel.edges.distance, rtol=1e-6)
    views = pq.read_table(tmp_path / "views.parquet").to_pydict()
    for col in ("anchor_idx", "perturbed", "wiou_to_train"):
        assert len(views[col]) == sel.n_views
