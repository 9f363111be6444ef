"""SSIM map with a hand-written backward: numba kernels for the forward and the gradient.

Same value as :func:`freescale_core.recon.losses.ssim_map` (the reference: five separable
11-tap Gaussian blurs by ``F.conv2d``, valid mode) but one pass over the image per channel and
an analytic backward, so autograd neither stores nor replays the ten convolutions.

With the raw blurred moments ``m_x = g*x, m_y = g*y, m_xx = g*x^2, m_yy = g*y^2,
m_xy = g*xy`` (``g*`` = valid-mode Gaussian blur) the SSIM of a window is
``S = A1 A2 / (B1 B2)`` with ``A1 = 2 m_x m_y + C1``, ``A2 = 2 (m_xy - m_x m_y) + C2``,
``B1 = m_x^2 + m_y^2 + C1``, ``B2 = m_xx - m_x^2 + m_yy - m_y^2 + C2``, so

* ``dS/dm_x  = 2 m_y (A2 - A1) / (B1 B2) + 2 m_x S (1/B2 - 1/B1)``
* ``dS/dm_xx = -S / B2``
* ``dS/dm_xy = 2 A1 / (B1 B2)``

and for an upstream gradient ``G`` of the map, with ``g^T`` the transposed (full-mode) blur,
``dL/dx = g^T(G dS/dm_x) + 2 x g^T(G dS/dm_xx) + y g^T(G dS/dm_xy)`` (the same with x and y
swapped for ``dL/dy``). The forward stores the three (or six) ``dS/dm`` maps when a gradient is
needed. Work is split over channels (``prange``), each channel's arithmetic is sequential, so
the result does not depend on the numba thread count.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from freescale_core.recon.ssim_window import (
    SSIM_C1,
    SSIM_C2,
    SSIM_SIGMA,
    SSIM_WINDOW,
    gaussian_window,
)


@njit(parallel=True, cache=True)
def _ssim_fwd(x, y, w, c1, c2, want_dx, want_dy, smap, dx_maps, dy_maps):
    """``x, y [C, H, W]``; writes ``smap [C, Hv, Wv]`` and, if wanted, ``dx_maps [3, C, Hv, Wv]``
    (dS/dm_x, dS/dm_xx, dS/dm_xy) and ``dy_maps`` (dS/dm_y, dS/dm_yy, dS/dm_xy)."""
    nc, h, wd = x.shape
    k = w.shape[0]
    hv, wv = h - k + 1, wd - k + 1
    one = x.dtype.type(1.0)
    two = x.dtype.type(2.0)
    for c in prange(nc):
        # row pass: five moments, valid along the row, every row kept
        rx = np.zeros((h, wv), x.dtype)
        ry = np.zeros((h, wv), x.dtype)
        rxx = np.zeros((h, wv), x.dtype)
        ryy = np.zeros((h, wv), x.dtype)
        rxy = np.zeros((h, wv), x.dtype)
        for i in range(h):
            for t in range(k):
                wt = w[t]
                for j in range(wv):
                    a = x[c, i, j + t]
                    b = y[c, i, j + t]
                    rx[i, j] += wt * a
                    ry[i, j] += wt * b
                    rxx[i, j] += wt * (a * a)
                    ryy[i, j] += wt * (b * b)
                    rxy[i, j] += wt * (a * b)
        # column pass into one output row at a time, then the SSIM of that row
        mx = np.empty(wv, x.dtype)
        my = np.empty(wv, x.dtype)
        mxx = np.empty(wv, x.dtype)
        myy = np.empty(wv, x.dtype)
        mxy = np.empty(wv, x.dtype)
        for i in range(hv):
            mx[:] = 0
            my[:] = 0
            mxx[:] = 0
            myy[:] = 0
            mxy[:] = 0
            for t in range(k):
                wt = w[t]
                for j in range(wv):
                    mx[j] += wt * rx[i + t, j]
                    my[j] += wt * ry[i + t, j]
                    mxx[j] += wt * rxx[i + t, j]
                    myy[j] += wt * ryy[i + t, j]
                    mxy[j] += wt * rxy[i + t, j]
            for j in range(wv):
                ux, uy = mx[j], my[j]
                sxx = mxx[j] - ux * ux
                syy = myy[j] - uy * uy
                sxy = mxy[j] - ux * uy
                a1 = two * ux * uy + c1
                a2 = two * sxy + c2
                b1 = ux * ux + uy * uy + c1
                b2 = sxx + syy + c2
                s = (a1 * a2) / (b1 * b2)
                smap[c, i, j] = s
                if want_dx or want_dy:
                    bb = b1 * b2
                    dxy = two * a1 / bb
                    dsq = -s / b2
                    q = two * s * (one / b2 - one / b1)
                    if want_dx:
                        dx_maps[0, c, i, j] = two * uy * (a2 - a1) / bb + ux * q
                        dx_maps[1, c, i, j] = dsq
                        dx_maps[2, c, i, j] = dxy
                    if want_dy:
                        dy_maps[0, c, i, j] = two * ux * (a2 - a1) / bb + uy * q
                        dy_maps[1, c, i, j] = dsq
                        dy_maps[2, c, i, j] = dxy


@njit(parallel=True, cache=True)
def _ssim_bwd(g, maps, x, y, w, out):
    """``out [C, H, W] = g^T(g dS/dm_x) + 2 x g^T(g dS/dm_xx) + y g^T(g dS/dm_xy)`` with
    ``g [C, Hv, Wv]`` the upstream gradient and ``maps [3, C, Hv, Wv]`` from the forward
    (call with x and y swapped and the dy maps for the gradient of y)."""
    nc, h, wd = x.shape
    k = w.shape[0]
    hv, wv = h - k + 1, wd - k + 1
    two = x.dtype.type(2.0)
    for c in prange(nc):
        # transposed column pass: scatter each valid row into k full rows
        ta = np.zeros((h, wv), x.dtype)
        tb = np.zeros((h, wv), x.dtype)
        tc = np.zeros((h, wv), x.dtype)
        ga = np.empty(wv, x.dtype)
        gb = np.empty(wv, x.dtype)
        gc = np.empty(wv, x.dtype)
        for i in range(hv):
            for j in range(wv):
                gg = g[c, i, j]
                ga[j] = gg * maps[0, c, i, j]
                gb[j] = gg * maps[1, c, i, j]
                gc[j] = gg * maps[2, c, i, j]
            for t in range(k):
                wt = w[t]
                for j in range(wv):
                    ta[i + t, j] += wt * ga[j]
                    tb[i + t, j] += wt * gb[j]
                    tc[i + t, j] += wt * gc[j]
        # transposed row pass, then combine
        fa = np.empty(wd, x.dtype)
        fb = np.empty(wd, x.dtype)
        fc = np.empty(wd, x.dtype)
        for i in range(h):
            fa[:] = 0
            fb[:] = 0
            fc[:] = 0
            for t in range(k):
                wt = w[t]
                for j in range(wv):
                    fa[j + t] += wt * ta[i, j]
                    fb[j + t] += wt * tb[i, j]
                    fc[j + t] += wt * tc[i, j]
            for j in range(wd):
                out[c, i, j] = fa[j] + two * x[c, i, j] * fb[j] + y[c, i, j] * fc[j]


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _FusedSSIMMap(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y):  # x, y [C, H, W], same dtype, CPU
        xn, yn = _np(x), _np(y)
        nc, h, wd = xn.shape
        hv, wv = h - SSIM_WINDOW + 1, wd - SSIM_WINDOW + 1
        w = gaussian_window(SSIM_WINDOW, SSIM_SIGMA, x.dtype).numpy()
        want_dx, want_dy = bool(ctx.needs_input_grad[0]), bool(ctx.needs_input_grad[1])
        smap = np.empty((nc, hv, wv), xn.dtype)
        dxm = np.empty((3, nc, hv, wv) if want_dx else (3, 1, 1, 1), xn.dtype)
        dym = np.empty((3, nc, hv, wv) if want_dy else (3, 1, 1, 1), xn.dtype)
        dt = xn.dtype.type
        _ssim_fwd(xn, yn, w, dt(SSIM_C1), dt(SSIM_C2), want_dx, want_dy, smap, dxm, dym)
        ctx.save_for_backward(x, y)
        ctx.np_saved = (xn, yn, w, dxm, dym)
        return torch.from_numpy(smap)

    @staticmethod
    def backward(ctx, grad):
        ctx.saved_tensors  # noqa: B018  (raises if an input was modified in place since)
        xn, yn, w, dxm, dym = ctx.np_saved
        gn = _np(grad.to(torch.from_numpy(xn).dtype))
        gx = gy = None
        if ctx.needs_input_grad[0]:
            out = np.empty_like(xn)
            _ssim_bwd(gn, dxm, xn, yn, w, out)
            gx = torch.from_numpy(out)
        if ctx.needs_input_grad[1]:
            out = np.empty_like(yn)
            _ssim_bwd(gn, dym, yn, xn, w, out)
            gy = torch.from_numpy(out)
        return gx, gy


def fused_ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """:func:`freescale_core.recon.losses.ssim_map` (``[H, W, C]`` images in [0, 1] ->
    ``[C, H - 10, W - 10]``) by the numba kernels; differentiable in both images (CPU,
    float32 or float64)."""
    x = img.permute(2, 0, 1)
    y = ref.permute(2, 0, 1).to(x.dtype)
    return _FusedSSIMMap.apply(x, y)
