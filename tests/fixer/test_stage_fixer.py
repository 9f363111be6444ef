"""The 'fixer' image rectifier in the free-view stage, its confidence in the store, and its
checkpoint errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freescale_core.fixer.model import CHECKPOINT_FORMAT, FixerCheckpointError, FixerNet
from schemas.fixer import FixerModelConfig
from schemas.freeview import FreeViewConfig, RectifierConfig

from tests.freeviews.test_freeviews import _run, setup  # noqa: F401 (fixture)


def _checkpoint(path, **model):
    cfg = FixerModelConfig(**model)
    torch.manual_seed(0)
    net = FixerNet(cfg)
    torch.save(dict(format=CHECKPOINT_FORMAT, model=net.state_dict(),
                    model_config=cfg.model_dump(mode="json")), path)
    return path


def test_stage_with_the_fixer_keeps_renders_and_confidence(setup, tmp_path):  # noqa: F811
    ck = _checkpoint(tmp_path / "fixer.pt", head="blend", k=2, levels=2, unshuffle=2)
    cfg = FreeViewConfig(rectifier=RectifierConfig(backend="fixer",
                                                   params={"checkpoint": str(ck)}))
    res = _run(setup, cfg)
    final = [r for r in res.records if r.final]
    assert final and all(r.rectifier == "fixer" for r in final)
    assert len(res.confidence) == res.n_final
    for rgb, raw, c in zip(res.rgb, res.rgb_render, res.confidence):
        assert c.shape == rgb.shape[:2] and np.all((c > 0) & (c < 1))
        assert not np.array_equal(rgb, raw)  # the blend at init mixes in the warps
    none = _run(setup, FreeViewConfig(rectifier=RectifierConfig(backend="none")))
    assert none.confidence == []


def test_missing_or_mismatched_checkpoint_names_the_file(setup, tmp_path):  # noqa: F811
    from freescale_core.freeviews.rectify_image import make_rectifier

    missing = tmp_path / "nope.pt"
    with pytest.raises(FixerCheckpointError, match="nope.pt"):
        make_rectifier(RectifierConfig(backend="fixer", params={"checkpoint": str(missing)}))
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(FixerCheckpointError, match="bad.pt.*not a fixer checkpoint"):
        make_rectifier(RectifierConfig(backend="fixer", params={"checkpoint": str(bad)}))
    ck = _checkpoint(tmp_path / "k1.pt", k=1)
    st = torch.load(ck, weights_only=False)
    st["model_config"]["k"] = 2  # weights for k=1, config says k=2
    torch.save(st, ck)
    with pytest.raises(FixerCheckpointError, match="k1.pt"):
        make_rectifier(RectifierConfig(backend="fixer", params={"checkpoint": str(ck)}))


def test_confidence_and_raw_renders_are_published(setup, tmp_path):  # noqa: F811
    import zarr

    from freescale_core.store import layout

    ck = _checkpoint(tmp_path / "fixer.pt", head="blend", k=2, levels=2, unshuffle=2)
    res = _run(setup, FreeViewConfig(rectifier=RectifierConfig(
        backend="fixer", params={"checkpoint": str(ck)})))
    # the freeviews part of write_scene_outputs, on a bare zarr group
    root = zarr.open_group(str(tmp_path / "a.zarr"), mode="w")
    layout.write_free_view_arrays(root, res, view_ids=np.arange(res.n_final))
    g = root["freeviews"]
    assert g["confidence"].shape == g["rgb"].shape[:3] == g["rgb_render"].shape[:3]
    c = np.asarray(g["confidence"][0])
    assert c.max() > 0 and np.abs(c / 255.0 - res.confidence[0]).max() <= 0.5 / 255 + 1e-6


def test_the_shipped_checkpoint_loads_and_matches_the_default_model():
    from freescale_core.freeviews.rectify_image import FixerRectifier, shipped_checkpoint

    assert shipped_checkpoint().is_file()
    fx = FixerRectifier()
    assert fx.model.cfg == FixerModelConfig()  # the defaults are the shipped model's
    assert fx.meta["holdout_scenes"] == [] and len(fx.meta["train_scenes"]) == 17


def test_trust_scores_the_fixed_image(setup, tmp_path):  # noqa: F811
    ck = _checkpoint(tmp_path / "fixer.pt", head="blend", k=2, levels=2, unshuffle=2)
    res = _run(setup, FreeViewConfig(rectifier=RectifierConfig(
        backend="fixer", params={"checkpoint": str(ck)})))
    final = [r for r in res.records if r.final]
    assert all(np.isfinite(r.pred_psnr_rectified) for r in final)
    assert any(r.pred_psnr_rectified != r.pred_psnr for r in final)  # scored anew
    none = _run(setup, FreeViewConfig(rectifier=RectifierConfig(backend="none")))
    assert all(r.pred_psnr_rectified == r.pred_psnr for r in none.records if r.final)


def test_shards_carry_the_fixers_confidence(tmp_path):
    from freescale_core.store.shards import pack_scene

    class _Views:  # two views: a photo and a free view the fixer made
        view_id = np.array([0, 1])
        is_free = np.array([False, True])
        mode = ["train", "orbit"]
        capture_index = np.array([0, -1])
        score_f = brisque = np.zeros(2)

        def __len__(self):
            return 2

        class cameras:  # noqa: N801
            fx = fy = np.array([40.0, 40.0])
            cx, cy = np.array([16.0, 16.0]), np.array([12.0, 12.0])
            width, height = np.array([32, 32]), np.array([24, 24])
            world_from_cam = np.tile(np.eye(4), (2, 1, 1))

    class _Fvs:
        scene_id = "s"

        def dataset_views(self):
            return _Views()

        def rgb(self, vid):
            return np.full((24, 32, 3), 100, np.uint8)

        def confidence(self, vid):
            return None if vid == 0 else np.full((24, 32), 0.5, np.float32)

        def graph(self):
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.float32)

    p = pack_scene(_Fvs(), 16)
    assert p.confidence.shape == (2, 16, 16)
    assert np.all(p.confidence[0] == 255) and np.all(p.confidence[1] == 128)
