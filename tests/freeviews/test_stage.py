"""The free-view stage adapter renders with the reconstruction's background and backend."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from freescale_core.freeviews.run import make_render_fn
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
    import freescale_core.freeviews.run as stage_mod
    import freescale_core.scene.ply as ply_mod
    import tasks.scene_tasks as st

    seen = {}

    def fake_stage(*args, **kw):
        seen.update(kw)
        return SimpleNamespace(counts={"n_free_views": 0})

    monkeypatch.setattr(stage_mod, "run_free_view_stage", fake_stage)
    monkeypatch.setattr(ply_mod, "read_ply", lambda *a, **k: None)
    monkeypatch.setattr(ply_mod, "read_background",  # no PLY here: the configured colour
                        lambda path, default=(0.0, 0.0, 0.0), scene_id=None: tuple(default))
    scene = SimpleNamespace(views_for=lambda split: (None, None))
    monkeypatch.setattr(st, "load_stage_output", lambda *a, **k: scene)
    monkeypatch.setattr(st, "run_stage", lambda root, sid, stage, cfg, up, mods, seed, compute:
                        compute(tmp_path))
    cfg = PipelineConfig.from_preset("fast", {"recon": {"background": [1.0, 1.0, 1.0],
                                                        "raster_backend": "reference"}})
    ref = SimpleNamespace(scene_id="s", result={"train_scale": 1.0})
    st.freeviews.fn(str(tmp_path), ref, ref, ref, str(tmp_path), cfg)
    assert tuple(seen["background"]) == (1.0, 1.0, 1.0)
    assert seen["backend"] == "reference"


def _plane_of_gaussians(rng, n=600) -> Gaussians:
    """A textured, slightly bumpy sheet of Gaussians around z = 4 (a scene every camera of
    :func:`test_stage_batched_rasterizer_renders_give_the_single_view_table` sees)."""
    xy = rng.uniform(-2.5, 2.5, (n, 2))
    z = 4.0 + 0.2 * np.sin(2 * xy[:, :1]) + rng.normal(0, 0.02, (n, 1))
    sh = np.zeros((n, 1, 3))
    sh[:, 0] = rng.uniform(-1.5, 1.5, (n, 3))
    return Gaussians(means=np.concatenate([xy, z], 1), log_scales=np.full((n, 3), -2.3),
                     quats_wxyz=np.tile([1.0, 0, 0, 0], (n, 1)),
                     opacity_logits=np.full(n, 3.0), sh=sh)


def test_stage_batched_rasterizer_renders_give_the_single_view_table():
    """The stage with the rasterizer's batch (``make_render_fn(...).batch``, one call per
    batch) against the same render function without it (view by view): the same table,
    trust scores included, and the same images, bit for bit."""
    from freescale_core.freeviews.run import run_freeviews
    from freescale_core.geometry.cameras import Cameras
    from schemas.freeview import FreeViewConfig, RectifierConfig
    from tests.freeviews.test_freeviews import _records_equal
    from tests.freeviews.test_rectify import cam

    rng = np.random.default_rng(3)
    g = _plane_of_gaussians(rng)
    fn = make_render_fn(g, background=(0.0, 0.0, 0.0), backend="cpu")
    W, H, f = 40, 30, 34.0
    train = Cameras(np.stack([cam([x, y, 0.0]) for x in (-0.8, 0.0, 0.8) for y in (-0.4, 0.4)]),
                    f, f, W / 2, H / 2, W, H)
    photos = [np.round(fn(train.world_from_cam[i], f, f, W / 2, H / 2, W, H)[0] * 255
                       ).astype(np.uint8) for i in range(len(train))]
    cands = Cameras(np.stack([cam([0.3, 0.1, 0.5]), cam([-0.5, 0.2, 0.8]),
                              cam([0.0, 0.0, 0.2], target=(0.0, 0.0, -4.0)),  # looks away
                              cam([0.6, -0.3, 1.0], target=(2.5, 0.0, 4.0)),
                              cam([-0.2, -0.2, 0.3])]), f, f, W / 2, H / 2, W, H)
    selected = np.arange(len(cands))
    cfg = FreeViewConfig(rectifier=RectifierConfig(backend="reproject"))

    def single(*a):
        return fn(*a)

    calls = []

    def batched(*a):
        return fn(*a)

    def batch(*a):
        calls.append(len(a[0]))
        return fn.batch(*a)

    batched.batch = batch
    want = run_freeviews(train, lambda i: photos[i], cands, selected, None, single, cfg)
    got = run_freeviews(train, lambda i: photos[i], cands, selected, None, batched, cfg)
    assert calls and calls[0] == len(selected)
    assert got.counts == want.counts and got.counts["passed"] >= 2
    assert np.isfinite([r.pred_psnr for r in got.records]).all()
    for ra, rb in zip(want.records, got.records):
        _records_equal(ra, rb)
    for a, b in zip(want.rgb + want.depth, got.rgb + got.depth):
        assert np.array_equal(a, b)
