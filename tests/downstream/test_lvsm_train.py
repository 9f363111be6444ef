"""LVSM training loop (freescale_core.downstream.lvsm.train): loss falls, resume equals an
uninterrupted run, determinism, the lr schedule, files written."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from freescale_core.downstream.lvsm.data import (
    SceneTensors,
    add_views,
    collate,
    from_shard_record,
    load_sample_scene,
)
from freescale_core.downstream.lvsm.sampler import ViewSampler
from freescale_core.downstream.lvsm.train import lr_factor, train_lvsm
from freescale_core.scene.family import write_family
from schemas.lvsm import LVSMSamplerConfig, TrainLVSMConfig
from schemas.scene_family import SceneFamilyConfig

W, H = 32, 24


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> list[SceneTensors]:
    dirs = write_family(tmp_path_factory.mktemp("fam"), 3, seed=0,
                        family=SceneFamilyConfig(layout="random", path="arc"),
                        n_views=10, width=64, height=48, n_points=50)
    return [load_sample_scene(d, W, H) for d in dirs]


def _cfg(**kw) -> TrainLVSMConfig:
    base = dict(steps=20, batch_size=4, lr=2e-3, warmup_steps=3, eval_every=10, ckpt_every=5,
                eval_samples=4, log_every=5,
                model_overrides=dict(d_model=32, n_layers=2, n_heads=2, image_size=32),
                sampler=LVSMSamplerConfig(n_input=2, n_target=1, warmup_steps=10,
                                          use_free_views=False))
    return TrainLVSMConfig(**{**base, **kw})


def _params(model) -> list[torch.Tensor]:
    return [p.detach().clone() for p in model.parameters()]


def test_lr_schedule():
    f = [lr_factor(s, 10, 110) for s in range(110)]
    assert f[0] == pytest.approx(0.1) and f[9] == pytest.approx(1.0)
    assert f[10] == pytest.approx(1.0) and f[60] == pytest.approx(0.5)
    assert all(a >= b for a, b in zip(f[10:], f[11:]))  # cosine decays monotonically
    assert lr_factor(110, 10, 110, 0.1) == pytest.approx(0.1)


def test_smoke_loss_falls_and_files(scenes, tmp_path):
    res = train_lvsm(scenes[:2], _cfg(steps=30), seed=0, out_dir=tmp_path / "run",
                     eval_scenes=scenes[2:], log=None)
    tr = [r["loss"] for r in res.history["train"]]
    assert len(tr) == 30
    assert np.mean(tr[-5:]) < 0.7 * np.mean(tr[:5]), tr
    assert res.history["eval"] and res.history["eval"][-1]["step"] == 30
    assert (tmp_path / "run" / "loss.png").stat().st_size > 1000
    h = json.loads((tmp_path / "run" / "history.json").read_text())
    assert len(h["train"]) == 30 and "it_s" in h["train"][-1]


def test_resume_equals_uninterrupted_and_determinism(scenes, tmp_path):
    cfg = _cfg()
    straight = train_lvsm(scenes[:2], cfg, seed=1, out_dir=tmp_path / "a", log=None, plot=False)
    again = train_lvsm(scenes[:2], cfg, seed=1, out_dir=None, log=None)
    for p, q in zip(_params(straight.model), _params(again.model)):
        torch.testing.assert_close(p, q, rtol=0, atol=0)

    class Killed(Exception):
        pass

    def kill(step, _rec):
        if step == 13:  # after the step-10 checkpoint: steps 11-13 are lost and redone
            raise Killed

    with pytest.raises(Killed):
        train_lvsm(scenes[:2], cfg, seed=1, out_dir=tmp_path / "b", log=None, callback=kill)
    resumed = train_lvsm(scenes[:2], cfg, seed=1, out_dir=tmp_path / "b", log=None,
                         plot=False)
    assert resumed.resumed_from == 10
    for p, q in zip(_params(straight.model), _params(resumed.model)):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
    assert [r["loss"] for r in resumed.history["train"]] == \
        [r["loss"] for r in straight.history["train"]]
    other = train_lvsm(scenes[:2], cfg, seed=2, out_dir=None, log=None)
    assert any(not torch.equal(p, q) for p, q in zip(_params(straight.model),
                                                     _params(other.model)))
    with pytest.raises(ValueError, match="another config or seed"):
        train_lvsm(scenes[:2], cfg, seed=3, out_dir=tmp_path / "b", log=None)


def test_free_views_weights_and_adapter(scenes):
    sc = scenes[0]
    n = sc.views.n_views
    rgb = (sc.images[:3].numpy().transpose(0, 2, 3, 1) * 255).astype(np.uint8)
    K = sc.K[:3].numpy() * 2  # as if the free views were rendered at twice the size
    rgb2 = np.repeat(np.repeat(rgb, 2, axis=1), 2, axis=2)
    both = add_views(sc, rgb2, K, sc.world_from_cam[:3].numpy(),
                     edges=(np.arange(n), np.arange(n) % 3 + n, np.full(n, 0.6)))
    assert both.views.n_views == n + 3 and both.views.is_free[n:].all()
    torch.testing.assert_close(both.K[n:], sc.K[:3])
    torch.testing.assert_close(both.images[n:], sc.images[:3], atol=1 / 255, rtol=0)
    sampler = ViewSampler(LVSMSamplerConfig(n_input=2, n_target=2, graph_prob=1.0,
                                            random_free=True))
    rng = np.random.default_rng(0)
    items = [(both, sampler.sample(both.views, rng)) for _ in range(40)]
    b = collate(items)
    assert b["images"].shape == (40, 2, 3, H, W) and b["tgt_K"].shape == (40, 2, 4)
    free_t = torch.stack([torch.as_tensor(both.views.is_free[s.target_ids]) for _, s in items])
    assert free_t.any()
    torch.testing.assert_close(b["weight"][free_t], torch.full((int(free_t.sum()),), 0.3))
    rec = {"images": both.images, "fxfycxcy": both.K, "world_from_cam": both.world_from_cam,
           "is_free": both.views.is_free, "scene_id": "x"}
    back = from_shard_record(rec)
    np.testing.assert_array_equal(back.views.frame_index[:n], np.arange(n))
    assert back.scene_id == "x" and back.views.edges[0].size == n - 1
    with pytest.raises(ValueError, match="scene 'x'"):
        from_shard_record({**rec, "fxfycxcy": both.K[:2]})


def test_confidence_weights_the_loss_per_pixel(scenes):
    """With ``confidence_weight`` a pixel of confidence 0 teaches nothing: garbage there
    leaves the trained parameters as with a clean image; without the option it does not."""
    from freescale_core.downstream.lvsm.model import loss as lvsm_loss

    pred, tgt = torch.zeros(1, 1, 3, 2, 2), torch.ones(1, 1, 3, 2, 2)
    c = torch.tensor([[[[1.0, 0.0], [0.0, 0.0]]]])
    assert float(lvsm_loss(pred, tgt)) == pytest.approx(1.0)
    assert float(lvsm_loss(pred, tgt, pixel_weight=c)) == pytest.approx(0.25)
    assert float(lvsm_loss(pred, tgt, pixel_weight=torch.ones(1, 1, 2, 2))) == 1.0

    base = scenes[0]
    n = base.views.n_views
    rgb = (base.images[:3].permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    K, c2w = base.K[:3].numpy(), base.world_from_cam[:3].numpy()
    conf = np.full((3, H, W), 255, np.uint8)
    conf[:, :, : W // 2] = 0  # the left half untrusted
    bad = rgb.copy()
    bad[:, :, : W // 2] = 255 - bad[:, :, : W // 2]  # ... and wrong there
    edges = (np.r_[np.arange(3), n + np.arange(3)], np.r_[n + np.arange(3), np.arange(3)],
             np.full(6, 0.5))
    clean = add_views(base, rgb, K, c2w, edges, confidence=conf)
    dirty = add_views(base, bad, K, c2w, edges, confidence=conf)
    assert clean.confidence.shape == (n + 3, H, W)
    assert float(clean.confidence[:n].min()) == 1.0 and float(clean.confidence[n:, :, 0].max()) == 0
    b = collate([(clean, ViewSampler(LVSMSamplerConfig(n_input=2, n_target=1)).sample(
        clean.views, np.random.default_rng(0)))])
    assert b["confidence"].shape == (1, 1, H, W)

    # one example by hand: captured inputs, a free-view target; garbage where confidence is 0
    from freescale_core.downstream.lvsm.model import LVSM
    from freescale_core.downstream.lvsm.sampler import Sample
    from freescale_core.downstream.lvsm.train import predict

    torch.manual_seed(0)
    model = LVSM(_cfg().model())
    smp = Sample(input_ids=np.array([0, 1]), target_ids=np.array([n]),
                 target_weight=np.ones(1, np.float32), source="frames")

    def grads(sc, weighted):
        model.zero_grad()
        bt = collate([(sc, smp)])
        l = lvsm_loss(predict(model, bt), bt["target"], bt["weight"],
                      bt["confidence"] if weighted else None)
        l.backward()
        return [p.grad.clone() for p in model.parameters()]

    assert all(torch.allclose(a, b) for a, b in zip(grads(clean, True), grads(dirty, True)))
    assert not all(torch.allclose(a, b) for a, b in zip(grads(clean, False), grads(dirty, False)))

    # the trainer's option (every target has its left half at confidence 0): on, the run
    # changes; with confidence 1 everywhere, on equals off
    half = torch.ones(n, H, W)
    half[:, :, : W // 2] = 0
    kw = dict(steps=4, eval_every=100, ckpt_every=100)

    def run(conf, on):
        sc = SceneTensors(base.views, base.images, base.K, base.world_from_cam, conf)
        r = train_lvsm([sc], _cfg(confidence_weight=on, **kw), seed=3, log=None)
        return _params(r.model)

    off = run(half, False)
    assert not all(torch.equal(a, b) for a, b in zip(run(half, True), off))
    assert all(torch.equal(a, b) for a, b in zip(run(torch.ones(n, H, W), True), off))
