"""The fixer network: shapes, gradients, odd sizes, identity at init, the checkpoint loader."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from freescale_core.fixer.data import model_input, n_input_channels
from freescale_core.fixer.infer import fix_views
from freescale_core.fixer.model import (CHECKPOINT_FORMAT, FixerCheckpointError, FixerNet,
                                        load_fixer, n_params)
from schemas.fixer import FixerModelConfig


def _perturbed(cfg: FixerModelConfig | None = None, seed: int = 0) -> FixerNet:
    torch.manual_seed(seed)
    m = FixerNet(cfg or FixerModelConfig())
    with torch.no_grad():
        m.head.weight.normal_(0, 0.05)
        m.head.bias.normal_(0, 0.05)
    return m


def test_shapes_and_ranges_default():
    cfg = FixerModelConfig()
    assert cfg.in_channels == n_input_channels(cfg.k) == 12
    m = _perturbed(cfg)
    x = torch.rand(2, 12, 32, 48)
    with torch.no_grad():
        fixed, conf = m(x)
    assert fixed.shape == (2, 3, 32, 48) and conf.shape == (2, 1, 32, 48)
    assert float(fixed.min()) >= 0 and float(fixed.max()) <= 1
    assert float(conf.min()) > 0 and float(conf.max()) < 1
    assert n_params(m) <= 1_000_000


@pytest.mark.parametrize("hw", [(37, 53), (13, 9), (40, 48)])
@pytest.mark.parametrize("unshuffle", [1, 2])
def test_odd_sizes_are_padded_and_cropped(hw, unshuffle):
    m = _perturbed(FixerModelConfig(unshuffle=unshuffle))
    H, W = hw
    x = torch.rand(1, 12, H, W)
    fixed, conf = m(x)
    assert fixed.shape == (1, 3, H, W) and conf.shape == (1, 1, H, W)
    # the crop keeps the top-left: the output at a pixel is the one of the padded input there
    m2 = m.multiple
    Hp, Wp = H + (-H) % m2, W + (-W) % m2
    mode = "reflect" if (Hp - H) < H and (Wp - W) < W else "replicate"
    xp = torch.nn.functional.pad(x, (0, Wp - W, 0, Hp - H), mode=mode)
    fp, _ = m(xp)
    assert torch.allclose(fp[..., :H, :W], fixed, atol=1e-6)


def test_gradients_reach_every_parameter():
    m = _perturbed()
    x = torch.rand(2, 12, 24, 24)
    fixed, conf = m(x)
    (fixed.mean() + conf.mean()).backward()
    missing = [n for n, p in m.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    assert not missing
    assert all(float(p.grad.abs().sum()) > 0 for p in m.parameters())


def test_identity_at_init():
    """Zero-initialised head: an untrained fixer returns the render exactly, confidence 0.5."""
    torch.manual_seed(3)
    m = FixerNet(FixerModelConfig(head="residual")).eval()
    x = torch.rand(2, 12, 20, 28)
    fixed, conf = m(x)
    assert torch.equal(fixed, x[:, :3])
    assert torch.allclose(conf, torch.full_like(conf, 0.5))


def test_wrong_channel_count_is_a_clear_error():
    m = FixerNet(FixerModelConfig(k=2))
    with pytest.raises(ValueError, match="12"):
        m(torch.rand(1, 8, 16, 16))


def test_fix_views_matches_the_model():
    rng = np.random.default_rng(0)
    N, H, W = 3, 20, 24
    render, alpha = rng.random((N, H, W, 3)), rng.random((N, H, W))
    warps, ww = rng.random((N, 1, H, W, 3)), rng.random((N, 1, H, W))  # 1 warp: padded to k=2
    m = _perturbed()
    f, c = fix_views(m, render, alpha, warps, ww, batch_size=2)
    assert f.shape == (N, H, W, 3) and c.shape == (N, H, W)
    x = torch.from_numpy(model_input(render[1], alpha[1], warps[1], ww[1], 2))[None]
    with torch.no_grad():
        f1, c1 = m(x)
    np.testing.assert_allclose(f[1], f1[0].permute(1, 2, 0).numpy(), atol=1e-6)
    np.testing.assert_allclose(c[1], c1[0, 0].numpy(), atol=1e-6)


# ------------------------------------------------------------------- checkpoint loader
def _save(path, model: FixerNet, **extra):
    torch.save(dict(format=CHECKPOINT_FORMAT, model=model.state_dict(),
                    model_config=model.cfg.model_dump(mode="json"), **extra), path)


def test_load_fixer_round_trip(tmp_path):
    m = _perturbed(FixerModelConfig(base_channels=8))
    _save(tmp_path / "f.pt", m, train_scenes=["a"])
    m2, meta = load_fixer(tmp_path / "f.pt", k=2)
    assert meta["train_scenes"] == ["a"] and not m2.training
    x = torch.rand(1, 12, 16, 16)
    with torch.no_grad():
        assert torch.equal(m(x)[0], m2(x)[0])


def test_load_fixer_missing_file(tmp_path):
    with pytest.raises(FixerCheckpointError, match="not found: .*nope.pt"):
        load_fixer(tmp_path / "nope.pt")


def test_load_fixer_not_a_checkpoint(tmp_path):
    (tmp_path / "junk.pt").write_bytes(b"not a torch file")
    with pytest.raises(FixerCheckpointError, match="junk.pt is not a fixer checkpoint"):
        load_fixer(tmp_path / "junk.pt")
    torch.save({"model": {}}, tmp_path / "other.pt")  # a torch file, but not ours
    with pytest.raises(FixerCheckpointError, match="other.pt is not a fixer checkpoint"):
        load_fixer(tmp_path / "other.pt")


def test_load_fixer_mismatched_k_and_channels(tmp_path):
    m = _perturbed(FixerModelConfig(k=1, base_channels=8))
    _save(tmp_path / "k1.pt", m)
    with pytest.raises(FixerCheckpointError, match="trained with k=1 .* asked for k=2"):
        load_fixer(tmp_path / "k1.pt", k=2)
    # weights of a k=1 model under a config that says k=2
    st = torch.load(tmp_path / "k1.pt", weights_only=False)
    st["model_config"]["k"] = 2
    torch.save(st, tmp_path / "lie.pt")
    with pytest.raises(FixerCheckpointError, match="weights take 8 input channels.*12"):
        load_fixer(tmp_path / "lie.pt")


def test_blend_head_mixes_only_valid_warps():
    import torch

    from freescale_core.fixer.model import FixerNet
    from schemas.fixer import FixerModelConfig

    torch.manual_seed(0)
    net = FixerNet(FixerModelConfig(head="blend", k=2, unshuffle=2, levels=2))
    H = W = 16
    render = torch.full((1, 3, H, W), 0.2)
    warp_a, warp_b = torch.full((1, 3, H, W), 0.9), torch.full((1, 3, H, W), 0.6)
    w_a = torch.ones(1, 1, H, W)
    w_b = torch.zeros(1, 1, H, W)  # no evidence: must never enter the mix
    x = torch.cat([render, torch.ones(1, 1, H, W), warp_a, w_a, warp_b, w_b], 1)
    with torch.no_grad():
        net.head.bias.view(net.n_out, 4)[4] = -20.0  # prefer any valid warp over the render
        f, c = net(x)
    assert torch.allclose(f, torch.full_like(f, 0.9), atol=1e-4)  # warp a only, never b
    assert c.shape == (1, 1, H, W)
    x.requires_grad_(True)
    f, c = FixerNet(FixerModelConfig(head="blend", k=2))(x)
    (f.mean() + c.mean()).backward()
    assert torch.isfinite(x.grad).all()
