"""The trainer's shape: view sources (per-view weight, mask, schedule), strategy hooks,
``train`` on prepared data, and ``reconstruct`` == ``train``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freescale_core.recon.losses import masked_photometric_loss, photometric_loss
from freescale_core.recon.strategy import MCMCStrategy, Strategy
from freescale_core.recon.trainer import _c2f_levels, prepare, reconstruct, train
from freescale_core.recon.views import CapturedViews, ScheduledViews
from schemas.recon import ReconConfig


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene

    d = write_sample_scene(tmp_path_factory.mktemp("tv") / "sample", n_views=8, width=64,
                           height=48, seed=0, n_points=300)
    return load_scene(d)


def _cfg(**kw):
    base = dict(max_iterations=40, min_iterations=40, densify_from=10, densify_every=10,
                densify_until=30, budget_min=200, cap_gaussians=400, threads=1,
                train_eval_views=2)
    base.update(kw)
    return ReconConfig.fast().model_copy(update=base)


def _flat(g):
    return np.concatenate([a.ravel() for a in (g.means, g.log_scales, g.quats_wxyz,
                                               g.opacity_logits, g.sh)])


def test_masked_loss_all_true_equals_plain_and_ignores_masked_pixels():
    rng = np.random.default_rng(0)
    a = torch.from_numpy(rng.random((30, 40, 3)))
    b = torch.from_numpy(rng.random((30, 40, 3)))
    full = torch.ones(30, 40, dtype=torch.bool)
    assert torch.allclose(masked_photometric_loss(a, b, full, 0.2),
                          photometric_loss(a, b, 0.2)[0])
    m = torch.zeros(30, 40, dtype=torch.bool)
    m[:, :20] = True
    b2 = b.clone()
    b2[:, 31:] = 0.0  # far from the mask (beyond the SSIM window's reach)
    assert torch.allclose(masked_photometric_loss(a, b, m, 0.2),
                          masked_photometric_loss(a, b2, m, 0.2))
    assert not torch.allclose(masked_photometric_loss(a, b, None, 0.2),
                              masked_photometric_loss(a, b2, None, 0.2))


def test_train_on_prepared_data_equals_reconstruct(tiny):
    cfg = _cfg()
    tr = [0, 2, 4, 6]
    a = reconstruct(tiny, cfg, seed=1, train_idx=tr)
    b = train(prepare(tiny, cfg, tr), cfg, seed=1)
    c = train(tiny, cfg, seed=1, view_source=None, strategy=MCMCStrategy(cfg), train_idx=tr)
    assert np.array_equal(_flat(a.gaussians), _flat(b.gaussians))
    assert np.array_equal(_flat(a.gaussians), _flat(c.gaussians))


def test_scheduled_pseudo_views_weights_and_hooks(tiny):
    cfg = _cfg()
    data = prepare(tiny, cfg, [0, 2, 4, 6])
    # a pseudo view: a held-out camera's image, half masked, weight 2 alpha, l = 0.5
    hold = prepare(tiny, cfg, [1])
    base = CapturedViews(data)
    pv = base.view(0)
    pv.image, pv.kind, pv.weight, pv.lambda_ssim = hold.images[0], "pseudo", 0.6, 0.5
    pv.mask = torch.zeros(pv.image.shape[:2], dtype=torch.bool)
    pv.mask[:, : pv.image.shape[1] // 2] = True
    src = ScheduledViews(base, [pv], start_step=20, probability=0.5)
    kinds, losses = [], {}

    def rec(step, state, info):
        kinds.append((step, info["view"].kind))
        losses[step] = info["loss"]

    calls = {"pre": 0, "post": 0}

    class Counting(Strategy):
        def step_pre_backward(self, state, step, info):
            calls["pre"] += 1
            return None

        def step_post_backward(self, state, step, info):
            calls["post"] += 1

    r = train(data, cfg, seed=0, view_source=src, strategy=Counting(), on_step=[rec])
    assert all(k == "captured" for s, k in kinds if s < 20)
    assert any(k == "pseudo" for s, k in kinds if s >= 20)
    assert calls == {"pre": 40, "post": 40}
    assert r.stats["n_gaussians"] == r.stats["n_gaussians_init"]  # no densification
    assert r.stats["densify"]["strategy"] == "none"
    # same seed, same schedule: identical
    r2 = train(data, cfg, seed=0, view_source=ScheduledViews(CapturedViews(data), [pv], 20, 0.5),
               strategy=Counting())
    assert np.array_equal(_flat(r.gaussians), _flat(r2.gaussians))


def test_coarse_to_fine_levels(tiny):
    cfg = _cfg(coarse_to_fine=((10, 3), (20, 2), (30, 8)))  # 48 px / 8 < 16: level dropped
    data = prepare(tiny, cfg, [0, 2, 4, 6])
    src = CapturedViews(data, _c2f_levels(cfg, data))
    assert [src.factor(s) for s in (1, 9, 10, 19, 20, 100)] == [3, 3, 2, 2, 1, 1]
    v4, v1 = src.view(1, 3), src.view(1, 1)
    assert v4.image.shape[:2] == (v4.camera.height, v4.camera.width)
    assert v4.camera.width == round(v1.camera.width / 3)
    assert v4.camera.fx == pytest.approx(v1.camera.fx * v4.camera.width / v1.camera.width)
    seen = []
    train(data, cfg, seed=0, on_step=[lambda s, st, i: seen.append(i["view"].camera.width)])
    assert seen[0] == v4.camera.width and seen[15] == src.view(0, 2).camera.width
    assert seen[-1] == v1.camera.width


def test_cpu_budget_clock(tiny):
    cfg = _cfg(max_iterations=10_000, min_iterations=10_000, max_seconds=0.5)
    r = train(tiny, cfg, seed=0, train_idx=[0, 2, 4, 6], clock="cpu")
    assert r.stats["clock"] == "cpu" and r.stats["iterations"] < 10_000
    assert "time budget" in r.stats["reasons"]["iterations"]
    with pytest.raises(ValueError, match="clock"):
        train(tiny, cfg, seed=0, train_idx=[0, 2], clock="gpu")


class _Fixed:
    """A view source serving the given view indices in turn (no randomness)."""

    def __init__(self, data, order):
        self.base, self.order, self.calls = CapturedViews(data), list(order), 0

    def next(self, step, rng):
        j = self.order[self.calls % len(self.order)]
        self.calls += 1
        return self.base.view(j)


def _grads_after_step_1(data, cfg, order):
    got = {}

    def rec(step, state, info):
        if step == 1:
            got.update({k: p.grad.detach().clone() for k, p in state.params.items()})

    src = _Fixed(data, order)
    cfg = cfg.model_copy(update={"max_iterations": 1, "min_iterations": 1})
    train(data, cfg, seed=3, view_source=src, strategy=MCMCStrategy(cfg), on_step=[rec])
    return got, src.calls


def test_a_batch_step_takes_the_mean_gradient_of_its_views(tiny):
    """Reference test: one step with ``batch_views=2`` backpropagates the mean of the two views'
    photometric gradients (+ the regulariser once), i.e. the mean of the two one-view grads."""
    cfg = _cfg(mcmc_noise_lr=0.0)
    data = prepare(tiny, cfg, [0, 2, 4, 6])
    ga, na = _grads_after_step_1(data, cfg, [1])
    gb, _ = _grads_after_step_1(data, cfg, [3])
    gab, nab = _grads_after_step_1(data, cfg.model_copy(update={"batch_views": 2}), [1, 3])
    assert (na, nab) == (1, 2)
    for k in ga:
        want = (ga[k] + gb[k]) / 2
        assert torch.allclose(gab[k], want, rtol=1e-5, atol=1e-6 * float(want.abs().max())), k
    assert any(not torch.allclose(ga[k], gb[k]) for k in ga)  # the two views differ


def test_batch_views_is_deterministic_and_changes_the_run(tiny):
    cfg = _cfg(batch_views=2)
    tr = [0, 2, 4, 6]
    a = reconstruct(tiny, cfg, seed=1, train_idx=tr)
    b = reconstruct(tiny, cfg, seed=1, train_idx=tr)
    one = reconstruct(tiny, _cfg(), seed=1, train_idx=tr)
    assert np.array_equal(_flat(a.gaussians), _flat(b.gaussians))
    assert a.stats["batch_views"] == 2 and one.stats["batch_views"] == 1
    assert a.stats["iterations"] == one.stats["iterations"] == 40
    assert not np.array_equal(_flat(a.gaussians), _flat(one.gaussians))
