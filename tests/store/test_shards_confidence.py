"""The shards' per-pixel ``confidence`` reaches LVSM training: ``load_shard_scenes`` feeds it
into ``SceneTensors.confidence``, so ``train.confidence_weight`` weighs the loss with it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freescale_core.store.reader import FreeViewSet
from freescale_core.store.shards import pack

R = 32


@pytest.fixture(scope="module")
def conf_shards(dataset_store, tmp_path_factory):
    """sample_a packed with a fixer-like confidence on its free views: 0 on the left half,
    1 on the right."""
    mp = pytest.MonkeyPatch()

    def conf(self, view_id):
        v = self.dataset_views()
        r = self._row(view_id)
        if not v.is_free[r]:
            return None
        h, w = int(v.cameras.height[r]), int(v.cameras.width[r])
        c = np.ones((h, w), np.float32)
        c[:, : w // 2] = 0.0
        return c

    mp.setattr(FreeViewSet, "confidence", conf)
    out = tmp_path_factory.mktemp("conf") / "out"
    try:
        pack(dataset_store, out, scenes=["sample_a"], resolution=R)
    finally:
        mp.undo()
    return out


def test_load_shard_scenes_feeds_the_confidence(conf_shards):
    from freescale_core.downstream.lvsm.from_shards import load_shard_scenes

    (sc,) = load_shard_scenes(conf_shards, image_size=16)
    free = sc.views.is_free
    if not free.any():
        pytest.skip("sample_a has no free views to carry a confidence")
    assert sc.confidence is not None and tuple(sc.confidence.shape) == (len(free), 16, 16)
    c = sc.confidence.numpy()
    assert (c[~free] == 1.0).all()                      # photos: full trust
    assert (c[free][:, :, :6] < 0.05).all() and (c[free][:, :, 10:] > 0.95).all()


def test_photos_only_shards_carry_no_confidence(dataset_store, tmp_path):
    """All 255 (no fixer map): None, so an unweighted run is unchanged."""
    from freescale_core.downstream.lvsm.from_shards import load_shard_scenes

    pack(dataset_store, tmp_path / "o", scenes=["sample_a"], resolution=R)
    (sc,) = load_shard_scenes(tmp_path / "o", image_size=16)
    assert sc.confidence is None


def test_confidence_weight_reaches_the_loss(conf_shards, tmp_path, monkeypatch):
    """``train.confidence_weight=true`` through the train-lvsm work: the loss gets the shards'
    per-pixel weights (0 where the map is 0)."""
    from freescale_core.downstream.lvsm import train as T
    from freescale_core.downstream.lvsm.from_shards import train_from_shards
    from schemas.lvsm import TrainLVSMShardsConfig

    seen = []
    real = T.lvsm_loss

    def spy(pred, target, weight=None, pixel_weight=None):
        seen.append(None if pixel_weight is None else pixel_weight.detach().clone())
        return real(pred, target, weight, pixel_weight)

    monkeypatch.setattr(T, "lvsm_loss", spy)
    cfg = TrainLVSMShardsConfig.model_validate({
        "heldout_tail": 0.0,
        "train": {"steps": 3, "batch_size": 4, "confidence_weight": True, "eval_every": 100,
                  "ckpt_every": 100, "model_overrides": {"d_model": 32, "n_layers": 1,
                                                         "image_size": 16}}})
    train_from_shards(conf_shards, tmp_path / "run", cfg, seed=0, log=None)
    weights = [w for w in seen if w is not None]
    assert weights, "the loss never got the confidence"
    w = torch.cat([x.reshape(-1) for x in weights])
    assert float(w.min()) < 0.05 and float(w.max()) == 1.0
