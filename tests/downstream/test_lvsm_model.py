"""LVSM model: shapes, attention oracle, gradients, ray geometry, invariance, training, seeds."""

from __future__ import annotations

import math

import pytest
import torch
from torch.func import functional_call

from freescale_core.downstream.lvsm.model import (
    LVSM, Block, attention, attention_reference, loss, normalize_poses, patchify, plucker_rays,
    psnr, unpatchify)
from schemas.lvsm import LVSMModelConfig

TINY = dict(d_model=16, n_layers=2, n_heads=2, image_size=16, patch_size=8)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny models gain nothing from intra-op threads, and on a busy 2-core machine the spinning
    thread pool made the gradcheck 10-20x slower (1.5 s -> 19-35 s)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def random_rotation(g: torch.Generator, n: int, dtype=torch.float64) -> torch.Tensor:
    """``[n, 3, 3]`` random proper rotations (QR of a Gaussian matrix)."""
    q, r = torch.linalg.qr(torch.randn(n, 3, 3, generator=g, dtype=dtype))
    q = q * torch.sign(torch.diagonal(r, dim1=-2, dim2=-1))[:, None, :]
    q[torch.det(q) < 0, :, 0] *= -1
    return q


def ring_cameras(g: torch.Generator, B: int, V: int, dtype=torch.float64) -> torch.Tensor:
    """``[B, V, 4, 4]`` cameras near a ring of radius 2 around the origin, looking inwards."""
    T = torch.zeros(B, V, 4, 4, dtype=dtype)
    for b in range(B):
        for v in range(V):
            a = 2 * math.pi * v / V + 0.3 * torch.rand(1, generator=g, dtype=dtype).item()
            c = torch.tensor([2 * math.cos(a), 0.3 * torch.randn(1, generator=g).item(),
                              2 * math.sin(a)], dtype=dtype)
            z = -c / c.norm()
            x = torch.linalg.cross(torch.tensor([0.0, 1.0, 0.0], dtype=dtype), z)
            x = x / x.norm()
            y = torch.linalg.cross(z, x)
            T[b, v, :3, :3] = torch.stack([x, y, z], dim=1)
            T[b, v, :3, 3] = c
            T[b, v, 3, 3] = 1
    return T


def batch(g: torch.Generator, B=2, Vi=3, Vt=2, H=16, W=16, dtype=torch.float32):
    """Random images + ring cameras + intrinsics: the five LVSM.forward arguments."""
    T = ring_cameras(g, B, Vi + Vt).to(dtype)  # [B, Vi+Vt, 4, 4]
    K = torch.tensor([W * 0.8, H * 0.8, W / 2, H / 2], dtype=dtype).expand(B, Vi + Vt, 4)
    images = torch.rand(B, Vi, 3, H, W, generator=g, dtype=dtype)
    return images, T[:, :Vi], K[:, :Vi], T[:, Vi:], K[:, Vi:]


def test_presets_and_validation():
    cpu, paper = LVSMModelConfig.preset("cpu"), LVSMModelConfig.preset("paper")
    assert (cpu.d_model, cpu.n_layers, cpu.n_heads, cpu.image_size, cpu.patch_size) == (
        128, 4, 4, 64, 8)
    assert (paper.d_model, paper.n_layers, paper.head_dim, paper.image_size) == (768, 24, 64, 256)
    assert LVSMModelConfig() == cpu
    with pytest.raises(ValueError, match="divisible"):
        LVSMModelConfig(d_model=10, n_heads=4)
    with pytest.raises(ValueError, match="unknown LVSM preset"):
        LVSMModelConfig.preset("huge")
    with pytest.raises(ValueError):
        LVSMModelConfig(dmodel=3)  # extra="forbid"


def test_output_shapes_and_range():
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    model = LVSM(**TINY)
    args = batch(g, B=2, Vi=3, Vt=2, H=16, W=24)
    out = model(*args)
    assert out.shape == (2, 2, 3, 16, 24)
    assert torch.isfinite(out).all() and (out > 0).all() and (out < 1).all()
    with pytest.raises(ValueError, match="divisible"):
        model(*batch(g, H=12, W=16))


def test_patchify_roundtrip():
    x = torch.randn(3, 5, 16, 24)
    t = patchify(x, 8)
    assert t.shape == (3, 6, 5 * 64)
    assert torch.equal(unpatchify(t, 8, 5, 16, 24), x)
    assert torch.equal(t[0, 1].reshape(5, 8, 8), x[0, :, :8, 8:16])  # patch (0, 1)


def test_sdpa_matches_reference_attention():
    g = torch.Generator().manual_seed(1)
    q, k, v = (torch.randn(2, 3, 17, 8, generator=g) for _ in range(3))
    torch.testing.assert_close(attention(q, k, v, "sdpa"), attention_reference(q, k, v),
                               atol=1e-5, rtol=0)
    with pytest.raises(ValueError):
        attention(q, k, v, "flash3")
    # whole block and whole model: the two attention paths agree
    block = Block(16, 2)
    x = torch.randn(2, 10, 16, generator=g)
    y_sdpa = block(x)
    block.attention_impl = "reference"
    torch.testing.assert_close(block(x), y_sdpa, atol=1e-5, rtol=0)
    torch.manual_seed(0)
    model = LVSM(**TINY)
    args = batch(g)
    y = model(*args)
    model.set_attention("reference")
    torch.testing.assert_close(model(*args), y, atol=1e-5, rtol=0)


def test_gradcheck_float64():
    g = torch.Generator().manual_seed(2)
    torch.manual_seed(0)
    model = LVSM(d_model=8, n_layers=1, n_heads=2, image_size=8, patch_size=4,
                 qk_norm="rmsnorm").double()
    images, Ti, Ki, Tt, Kt = batch(g, B=1, Vi=2, Vt=1, H=8, W=8, dtype=torch.float64)
    images.requires_grad_(True)
    params = {k: v.detach().clone().requires_grad_(True) for k, v in model.named_parameters()}
    names = ["blocks.0.q_norm.weight", "head.bias"]  # full Jacobians: a few seconds

    def f(images, *ps):
        return functional_call(model, {**params, **dict(zip(names, ps))}, (images, Ti, Ki, Tt, Kt))

    assert torch.autograd.gradcheck(f, (images, *[params[n] for n in names]), eps=1e-6,
                                    atol=1e-5)
    # every parameter (random projections: fast mode) and the target cameras
    all_names = list(params)

    def f_all(Tt, *ps):
        return functional_call(model, dict(zip(all_names, ps)), (images, Ti, Ki, Tt, Kt))

    Tt = Tt.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f_all, (Tt, *params.values()), eps=1e-6, atol=1e-5,
                                    fast_mode=True)


def test_plucker_ray_properties():
    g = torch.Generator().manual_seed(3)
    T = ring_cameras(g, 2, 3)
    K = torch.tensor([20.0, 25.0, 6.0, 5.0], dtype=torch.float64).expand(2, 3, 4)
    r = plucker_rays(T, K, 10, 12)  # [2, 3, 6, 10, 12]
    assert r.shape == (2, 3, 6, 10, 12)
    d, m = r[:, :, :3], r[:, :, 3:]
    torch.testing.assert_close(d.norm(dim=2), torch.ones(2, 3, 10, 12, dtype=torch.float64))
    torch.testing.assert_close((d * m).sum(dim=2), torch.zeros(2, 3, 10, 12, dtype=torch.float64))
    # moment = o x d: every ray passes through the camera centre o
    o = T[..., :3, 3][..., None, None]  # [2, 3, 3, 1, 1]
    torch.testing.assert_close(m, torch.linalg.cross(o.expand_as(d), d, dim=2))
    # identity camera, odd image, principal point at the centre pixel's centre: ray = +z
    eye = torch.eye(4, dtype=torch.float64)[None, None]
    K1 = torch.tensor([[[7.0, 9.0, 2.5, 1.5]]], dtype=torch.float64)  # 5 wide, 3 high
    r1 = plucker_rays(eye, K1, 3, 5)
    torch.testing.assert_close(r1[0, 0, :, 1, 2], torch.tensor([0, 0, 1, 0, 0, 0.0],
                                                               dtype=torch.float64))
    # OpenCV: the pixel right of centre looks along +x, the one below along +y
    assert r1[0, 0, 0, 1, 3] > 0 and r1[0, 0, 1, 2, 2] > 0


def test_normalize_poses_frame():
    g = torch.Generator().manual_seed(4)
    T = ring_cameras(g, 3, 5)
    N, s = normalize_poses(T, 3)
    c = N[:, :3, :3, 3]  # [3, 3, 3] input centres
    torch.testing.assert_close(c.mean(1), torch.zeros(3, 3, dtype=torch.float64))
    torch.testing.assert_close(c.norm(dim=-1).max(1).values, torch.ones(3, dtype=torch.float64))
    R = N[..., :3, :3]
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64)
                               .expand_as(R))
    # all inputs at one point: scale guarded to 1, no NaN
    T0 = T.clone()
    T0[:, :, :3, 3] = 1.5
    N0, s0 = normalize_poses(T0, 3)
    assert torch.isfinite(N0).all() and torch.equal(s0, torch.ones(3, dtype=torch.float64))


@pytest.mark.parametrize("rotate", [False, True])
def test_prediction_invariant_to_scene_similarity(rotate):
    g = torch.Generator().manual_seed(5)
    torch.manual_seed(0)
    model = LVSM(**TINY).double()
    images, Ti, Ki, Tt, Kt = batch(g, dtype=torch.float64)
    s, c = 3.7, torch.tensor([10.0, -4.0, 2.5], dtype=torch.float64)
    Q = random_rotation(g, 1)[0] if rotate else torch.eye(3, dtype=torch.float64)

    def move(T):
        out = T.clone()
        out[..., :3, :3] = Q @ T[..., :3, :3]
        out[..., :3, 3] = s * T[..., :3, 3] @ Q.T + c
        return out

    y0 = model(images, Ti, Ki, Tt, Kt)
    y1 = model(images, move(Ti), Ki, move(Tt), Kt)
    torch.testing.assert_close(y1, y0, atol=1e-5, rtol=0)


def test_loss_and_psnr():
    pred = torch.zeros(2, 3, 3, 4, 4)
    target = torch.zeros(2, 3, 3, 4, 4)
    target[0, 0] = 0.1  # mse 0.01 -> 20 dB
    assert psnr(pred, target)[0, 0].item() == pytest.approx(20.0)
    assert loss(pred, target).item() == pytest.approx(0.01 / 6)
    w = torch.tensor([[0.3, 1.0, 1.0], [1.0, 1.0, 1.0]])
    assert loss(pred, target, w).item() == pytest.approx(0.3 * 0.01 / 5.3)
    assert loss(pred, target, torch.zeros(2, 3)).item() == 0.0


def synthetic_views(g: torch.Generator, B: int, Vi=2, Vt=1, H=16, W=16):
    """Scenes whose every view is one random colour: inputs show it, targets must copy it."""
    images, Ti, Ki, Tt, Kt = batch(g, B=B, Vi=Vi, Vt=Vt, H=H, W=W)
    colour = torch.rand(B, 1, 3, 1, 1, generator=g)
    return colour.expand(B, Vi, 3, H, W), Ti, Ki, Tt, Kt, colour.expand(B, Vt, 3, H, W)


def test_training_smoke_loss_falls():
    g = torch.Generator().manual_seed(6)
    torch.manual_seed(0)
    model = LVSM(d_model=32, n_layers=2, n_heads=2, image_size=16, patch_size=8)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    data = [synthetic_views(g, 8) for _ in range(4)]
    losses = []
    for step in range(20):
        images, Ti, Ki, Tt, Kt, target = data[step % 4]
        pred = model(images, Ti, Ki, Tt, Kt)
        ell = loss(pred, target, torch.ones(8, 1))
        opt.zero_grad()
        ell.backward()
        opt.step()
        losses.append(ell.item())
    first, last = sum(losses[:4]) / 4, sum(losses[-4:]) / 4
    assert last < 0.5 * first, losses


def test_same_seed_same_output():
    g = torch.Generator().manual_seed(7)
    args = batch(g)
    outs = []
    for _ in range(2):
        torch.manual_seed(123)
        outs.append(LVSM(**TINY)(*args))
    assert torch.equal(outs[0], outs[1])
    torch.manual_seed(124)
    assert not torch.equal(LVSM(**TINY)(*args), outs[0])
