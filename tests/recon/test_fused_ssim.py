"""The fused SSIM (numba forward, analytic backward) against the reference ``F.conv2d`` SSIM:
same value (1e-5) and gradient (1e-4 relative), with and without a mask."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.recon.fused_ssim import fused_ssim_map
from freescale_core.recon.losses import masked_photometric_loss, ssim, ssim_map


def _random(h, w, seed):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, 3, generator=g)
    b = torch.rand(h, w, 3, generator=g)
    return a, b


def _real_looking(h, w, seed):
    """A smooth image with edges (blurred noise plus a step) and a close render of it, the
    regime of training (SSIM near 1, small variances: where float32 cancellation shows)."""
    g = torch.Generator().manual_seed(seed)
    n = torch.rand(1, 3, h, w, generator=g)
    k = torch.ones(3, 1, 5, 5) / 25
    ref = F.conv2d(F.pad(n, (2, 2, 2, 2), mode="replicate"), k, groups=3)[0].permute(1, 2, 0)
    ref[:, : w // 2] = 0.8 * ref[:, : w // 2] + 0.2
    img = (ref + 0.02 * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    return img.contiguous(), ref.contiguous()


def _compare(img, ref, mask=None):
    """Value and gradients (w.r.t. both images) of the loss by both implementations."""
    out = {}
    for impl in ("torch", "fused"):
        a = img.clone().requires_grad_(True)
        b = ref.clone().requires_grad_(True)
        if mask is None:
            v = ssim(a, b, impl)
        else:
            v = masked_photometric_loss(a, b, mask, 0.2, ssim_impl=impl)
        ga, gb = torch.autograd.grad(v, (a, b))
        out[impl] = (float(v.detach()), ga, gb)
    (v0, ga0, gb0), (v1, ga1, gb1) = out["torch"], out["fused"]
    assert abs(v0 - v1) <= 1e-5, (v0, v1)
    for g0, g1 in ((ga0, ga1), (gb0, gb1)):
        assert float((g0 - g1).abs().max()) <= 1e-4 * float(g0.abs().max()) + 1e-12


@pytest.mark.parametrize("h,w", [(16, 16), (11, 11), (37, 23), (96, 128), (384, 512)])
@pytest.mark.parametrize("kind", ["random", "real"])
def test_fused_equals_reference(h, w, kind):
    img, ref = (_random if kind == "random" else _real_looking)(h, w, h * 1000 + w)
    _compare(img, ref)
    # the map itself, without autograd (evaluation path): pointwise, float32 rounding of the
    # variances (m_xx - m_x^2) costs both implementations ~1e-4 against float64 on smooth
    # images, so each pixel is held to the reference's own error, the mean to 1e-5
    with torch.no_grad():
        s64 = ssim_map(img.double(), ref.double())
        t, u = ssim_map(img, ref, "torch").double(), ssim_map(img, ref, "fused").double()
    assert float((u - s64).abs().max()) <= 2 * float((t - s64).abs().max()) + 1e-6
    assert abs(float(u.mean()) - float(t.mean())) <= 1e-5


@pytest.mark.parametrize("h,w", [(16, 16), (40, 52), (384, 512)])
def test_fused_equals_reference_masked(h, w):
    img, ref = _real_looking(h, w, 7)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    mask = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (0.4 * min(h, w)) ** 2
    _compare(img, ref, mask)
    _compare(img, ref, torch.zeros(h, w, dtype=torch.bool))  # no window centre in the mask


@settings(max_examples=25, deadline=None)
@given(h=st.integers(11, 64), w=st.integers(11, 64), seed=st.integers(0, 2**16),
       real=st.booleans(), masked=st.booleans())
def test_fused_equals_reference_property(h, w, seed, real, masked):
    img, ref = (_real_looking if real else _random)(h, w, seed)
    mask = None
    if masked:
        mask = torch.rand(h, w, generator=torch.Generator().manual_seed(seed + 1)) < 0.7
    _compare(img, ref, mask)


def test_fused_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    a = torch.rand(13, 14, 2, generator=g, dtype=torch.float64, requires_grad=True)
    b = torch.rand(13, 14, 2, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(fused_ssim_map, (a, b), eps=1e-6, atol=1e-7, rtol=1e-5)
    # a mean over a weighted map (the masked loss's shape of upstream gradient)
    wts = torch.rand(2, 3, 4, generator=g, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x, y: (fused_ssim_map(x, y) * wts).sum(), (a, b))


def test_fused_matches_skimage():
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(0)
    a = rng.random((40, 52, 3))
    b = np.clip(a + 0.15 * rng.standard_normal((40, 52, 3)), 0, 1)
    ref = structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
                                use_sample_covariance=False, data_range=1.0, channel_axis=-1)
    assert float(ssim(torch.from_numpy(a), torch.from_numpy(b), "fused")) == pytest.approx(
        ref, abs=1e-3)
    assert float(ssim(torch.from_numpy(a).float(), torch.from_numpy(a).float(), "fused")
                 ) == pytest.approx(1.0, abs=1e-6)


def test_ssim_impl_rejects_unknown():
    a = torch.rand(16, 16, 3)
    with pytest.raises(ValueError, match="impl"):
        ssim_map(a, a, "cuda")


def test_fused_same_bits_any_thread_count():
    """Work is split over channels only, so the numba thread count does not change a bit."""
    import numba

    img, ref = _real_looking(40, 52, 5)
    out = []
    prev = numba.get_num_threads()
    try:
        for n in sorted({1, numba.config.NUMBA_NUM_THREADS}):
            numba.set_num_threads(n)
            a = img.clone().requires_grad_(True)
            s = ssim(a, ref, "fused")
            s.backward()
            out.append((s.detach(), a.grad))
    finally:
        numba.set_num_threads(prev)
    assert all(torch.equal(out[0][0], o[0]) and torch.equal(out[0][1], o[1]) for o in out)
