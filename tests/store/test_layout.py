"""The published layout: the view graph keeps the weights it was built with."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pyarrow.parquet as pq
import pytest

from freescale_core.select.run import run_selection
from freescale_core.store.layout import write_scene_outputs
from schemas.select import SelectConfig
from tests.select.test_select import _room


@pytest.mark.parametrize("mode", ["wiou", "pose_distance"])
def test_published_graph_has_its_weights(tmp_path, mode):
    g, cams = _room(n=6000, n_cams=12)
    cfg = SelectConfig.fast()
    cfg.graph.mode = mode
    sel = run_selection(g, cams, cfg, seed=1)
    names = [f"{i:03d}.png" for i in range(len(cams))]
    for n in names:
        (tmp_path / n).write_bytes(b"png")
    scene = SimpleNamespace(cameras=cams, image_names=names, capture_order=np.arange(len(cams)),
                            image_paths=[tmp_path / n for n in names], scene_id="room",
                            points_xyz=np.zeros((0, 3)), points_rgb=np.zeros((0, 3), np.uint8))
    (tmp_path / "out").mkdir()
    tmp_path = tmp_path / "out"
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
