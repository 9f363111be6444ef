"""The free-view stage adapter renders with the reconstruction's background and backend."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from freescale_core.freeviews.stage import make_render_fn
from freescale_core.scene.gaussians import Gaussians
from schemas.pipeline import PipelineConfig


def _one_gaussian() -> Gaussians:
    return Gaussians(means=np.array([[0.0, 0.0, 3.0]]), log_scales=np.full((1, 3), -3.0),
                     quats_wxyz=np.array([[1.0, 0, 0, 0]]), opacity_logits=np.array([4.0]),
                     sh=np.zeros((1, 1, 3)))


def test_render_fn_uses_the_background():
    g = _one_gaussian()
    pose = np.eye(4)
    for bg in ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)):
        rgb, _, alpha = make_render_fn(g, background=bg)(pose, 20.0, 20.0, 16.0, 16.0, 32, 32)
        empty = alpha < 1e-3
        assert empty.sum() > 100
        np.testing.assert_allclose(rgb[empty], np.broadcast_to(bg, rgb[empty].shape), atol=1e-3)


def test_free_view_task_passes_recon_background_and_backend(monkeypatch, tmp_path):
    """The task hands cfg.recon.background / raster_backend to the stage (was dropped)."""
    import freescale_core.freeviews.stage as stage_mod
    import freescale_core.scene.ply as ply_mod
    import tasks.scene_tasks as st

    seen = {}

    def fake_stage(*args, **kw):
        seen.update(kw)
        return SimpleNamespace(counts={"n_free_views": 0})

    monkeypatch.setattr(stage_mod, "run_free_view_stage", fake_stage)
    monkeypatch.setattr(ply_mod, "read_ply", lambda *a, **k: None)
    scene = SimpleNamespace(views_for=lambda split: (None, None))
    monkeypatch.setattr(st, "load_stage_output", lambda *a, **k: scene)
    monkeypatch.setattr(st, "run_stage", lambda root, sid, stage, cfg, up, mods, seed, compute:
                        compute(tmp_path))
    cfg = PipelineConfig.from_preset("fast", {"recon": {"background": [1.0, 1.0, 1.0],
                                                        "raster_backend": "reference"}})
    ref = SimpleNamespace(scene_id="s", result={"train_scale": 1.0})
    st.free_views.fn(str(tmp_path), ref, ref, ref, str(tmp_path), cfg)
    assert tuple(seen["background"]) == (1.0, 1.0, 1.0)
    assert seen["backend"] == "reference"
