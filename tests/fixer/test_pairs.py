"""Fixer training pairs: no held-out photo in its reconstruction, layout, resume."""

from __future__ import annotations

import numpy as np
import pytest

from freescale_core.eval import fixer_pairs as P
from freescale_core.fixer.data import load_pairs, model_input, n_input_channels
from schemas.fixer_pairs import PairsConfig


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    return write_sample_scene(tmp_path_factory.mktemp("s") / "scene", n_views=10, width=64,
                              height=48, seed=0)


class _FakeRecon:
    """Stands in for the trainer: Gaussians at the training views' sparse points, and a
    record of which views each reconstruction was given."""

    def __init__(self):
        self.calls = []

    def __call__(self, scene, cfg, seed, train_idx=None, checkpoint_every=0,
                 on_checkpoint=None, **kw):
        from freescale_core.recon.trainer import ReconResult
        from freescale_core.scene.gaussians import Gaussians

        self.calls.append((scene.scene_id, np.asarray(train_idx).copy()))
        xyz = np.asarray(scene.points_xyz, np.float32)[:400]
        n = len(xyz)
        g = Gaussians(xyz, np.full((n, 3), -3.0, np.float32),
                      np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
                      np.full(n, 2.0, np.float32), np.zeros((n, 1, 3), np.float32))
        if on_checkpoint is not None and checkpoint_every:
            for step in range(checkpoint_every, cfg.max_iterations, checkpoint_every):
                on_checkpoint(step, g, {})
        return ReconResult(g, {"iterations": cfg.max_iterations, "background": [0, 0, 0]})


@pytest.fixture
def fake_recon(monkeypatch):
    import freescale_core.recon.trainer as T

    f = _FakeRecon()
    monkeypatch.setattr(T, "reconstruct", f)
    return f


CFG = PairsConfig(folds=["every8", "ood", "oracle"], k=2, long_side=64, max_views_per_fold=3,
                  oracle_views=2)


def test_no_heldout_photo_enters_the_reconstruction_that_renders_it(tiny_scene, tmp_path,
                                                                     fake_recon):
    rows = P.make_scene_pairs(tiny_scene, tmp_path, CFG, seed=0)
    assert [r["fold"] for r in rows] == ["every8", "ood", "oracle"]
    pairs = load_pairs(tmp_path)
    assert pairs
    trained = {i: set(map(int, idx)) for i, (_, idx) in enumerate(fake_recon.calls)}
    for call, fold in zip(trained.values(), ["every8", "ood", "oracle"]):
        held = {int(s.meta["view_index"]) for s in pairs if s.meta["fold"] == fold}
        if fold == "oracle":  # targets are the exact renderer's images at off-path poses
            assert held == {-1}
            continue
        assert held and not (held & call), (fold, held & call)


def test_a_split_that_leaks_is_refused(tiny_scene, fake_recon, monkeypatch):
    from freescale_core.scene.io import load_scene

    scene = load_scene(tiny_scene)
    monkeypatch.setattr(type(scene), "split",
                        lambda self, kind="ood", **kw: (np.arange(len(self)), np.array([3])))
    with pytest.raises(P.LeakError, match="held-out views"):
        P.make_fold_pairs(scene, "every8", CFG)
    assert not fake_recon.calls  # refused before anything trained


def test_pair_layout_and_resume(tiny_scene, tmp_path, fake_recon):
    P.make_scene_pairs(tiny_scene, tmp_path, CFG.model_copy(update={"folds": ["every8"]}))
    pairs = load_pairs(tmp_path)
    s = pairs[0]
    H, W = s.hw
    assert (W, H) == (64, 48) and s.warps.shape == (2, H, W, 3)
    assert {p.meta["budget"] for p in pairs} == {0.33, 1.0}
    assert np.all((s.warp_weight >= 0) & (s.warp_weight <= 1))
    assert model_input(s.render, s.alpha, s.warps, s.warp_weight, 2).shape == (
        n_input_channels(2), H, W)
    n_calls = len(fake_recon.calls)
    rows = P.make_scene_pairs(tiny_scene, tmp_path, CFG.model_copy(update={"folds": ["every8"]}))
    assert rows[0]["kept"] and len(fake_recon.calls) == n_calls
    # another config is another key: remade
    rows = P.make_scene_pairs(tiny_scene, tmp_path,
                              CFG.model_copy(update={"folds": ["every8"], "k": 1}))
    assert not rows[0]["kept"] and len(fake_recon.calls) == n_calls + 1
    assert load_pairs(tmp_path)[0].warps.shape[0] == 1


def test_nearest_refs_is_pose_order():
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = [3.0, 0.1, 2.0, 1.0]
    assert list(P.nearest_refs(poses, np.eye(4), 3)) == [1, 3, 2]
