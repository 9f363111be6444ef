"""Numba kernels of the CPU rasterizer: projection, tile binning, blending, and their backward.

Pipeline (one view; N Gaussians, M of them visible, E Gaussian-tile pairs, T tiles):

1. ``project_fwd``  parallel over Gaussians: EWA projection, SH colour, tile rectangle.
2. depth sort of the M visible Gaussians (numpy, uint64 keys in ``cpu.py``); ``gather_rows``
   packs their records and tile rectangles front to back (a tight gather of scattered rows is
   faster than chasing them inside the binning loop: 16 vs 25 ms at 256 px / 300k).
3. ``bin_tiles``  keeps the bounding-box tiles the ellipse reaches (``_tile_rows``: exact
   ellipse-tile test and the pair's row range), then a counting sort of the E pairs into
   per-tile lists that stay depth-sorted; the 12-float record of every pair is copied
   tile-major (its last two floats: the pair's rows) so the blends stream through memory.
4. ``blend_fwd``  parallel over tiles: front-to-back compositing; per pixel it keeps the final
   transmittance and the number of list entries it consumed (the "last contributor", as 3DGS).
5. ``blend_bwd``  parallel over tiles: walks each tile list back to front, recovering T by
   division, and writes one 10-float gradient per pair, Gaussian-major (no atomics).
6. ``reduce_pairs`` sums each Gaussian's pair gradients (fixed order, float64);
   ``project_bwd`` back-propagates through the projection and SH to the five parameter tensors.

Inner blending loops run over the 16 pixels of a tile row with branch-free selects so that
LLVM vectorises them (see the comment above ``blend_fwd`` for what breaks that); ``exp`` is a
vectorisable polynomial (``_exp_neg``). Decisions (3-sigma, 1/255, T stop) are computed by the
same float32 expressions in forward and backward, and ``fastmath`` is off so that they stay
identical. docs/RASTERIZER.md has the measurements behind these choices.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import _common as c

F0 = np.float32(0.0)
F1 = np.float32(1.0)
FHALF = np.float32(0.5)
F_POWER_MAX = np.float32(c.POWER_MAX)
F_ALPHA_MIN = np.float32(c.ALPHA_MIN)
F_ALPHA_MAX = np.float32(c.ALPHA_MAX)
F_T_MIN = np.float32(c.T_MIN)
F_ALPHA_DEPTH_MIN = np.float32(c.ALPHA_DEPTH_MIN)
NEAR = c.NEAR
LOWPASS = c.LOWPASS
ALPHA_MIN64 = c.ALPHA_MIN
POWER_MAX64 = c.POWER_MAX
TILE = c.TILE
CHUNK = 1024  # Gaussians per parallel work item (scratch arrays are allocated per chunk)
NPAR = 10  # per-pair gradient: u, v, conic a, b, c, opacity, r, g, b, z
NPACK = 12  # packed per-Gaussian blend record: u, v, a, b, c, opacity, r, g, b, z, ex, ey

_LOG2E = np.float32(1.4426950408889634)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
_EXP_LO = np.float32(-8.0)
_P2 = np.float32(1.0 / 2.0)
_P3 = np.float32(1.0 / 6.0)
_P4 = np.float32(1.0 / 24.0)
_P5 = np.float32(1.0 / 120.0)
_P6 = np.float32(1.0 / 720.0)
_Q1 = np.float32(0.5)
_Q2 = np.float32(0.25)
_Q4 = np.float32(1.0 / 16.0)
_Q8 = np.float32(1.0 / 256.0)
_M1, _M2, _M4, _M8 = np.float32(-1.0), np.float32(-2.0), np.float32(-4.0), np.float32(-8.0)
_E2, _E4, _E8 = np.float32(2.0), np.float32(4.0), np.float32(8.0)

SH_C0, SH_C1 = c.SH_C0, c.SH_C1
C20, C21, C22, C23, C24 = c.SH_C2
C30, C31, C32, C33, C34, C35, C36 = c.SH_C3


@njit(inline="always", cache=True)
def _exp_neg(p):
    """exp(-p) in float32 for p >= 0 (vectorisable; p > 8 is treated as 8, p < 0 as 0).

    Cody-Waite reduction x = k ln2 + r, |r| <= ln2/2, degree-6 Taylor for exp(r) (truncation
    < 1.2e-7 relative) and 2^k, k in [-12, 0], from exact power-of-two float selects (integer
    bit tricks would stop LLVM from vectorising). Max relative error 2.3e-7 on [0, 4.6].
    """
    x = min(max(-p, _EXP_LO), F0)
    kf = np.floor(x * _LOG2E + FHALF)
    r = (x - kf * _LN2_HI) - kf * _LN2_LO
    e = F1 + r * (F1 + r * (_P2 + r * (_P3 + r * (_P4 + r * (_P5 + r * _P6)))))
    c = kf <= _M8
    s = _Q8 if c else F1
    kf = kf + (_E8 if c else F0)
    c = kf <= _M4
    s = s * (_Q4 if c else F1)
    kf = kf + (_E4 if c else F0)
    c = kf <= _M2
    s = s * (_Q2 if c else F1)
    kf = kf + (_E2 if c else F0)
    s = s * (_Q1 if kf <= _M1 else F1)
    return e * s


# --------------------------------------------------------------------------- SH
@njit(inline="always", cache=True)
def _sh_basis_into(x, y, z, out):
    """The 16 real SH basis values (3DGS order/constants) at unit direction (x, y, z) -> out."""
    xx, yy, zz = x * x, y * y, z * z
    out[0] = SH_C0
    out[1] = -SH_C1 * y
    out[2] = SH_C1 * z
    out[3] = -SH_C1 * x
    out[4] = C20 * x * y
    out[5] = C21 * y * z
    out[6] = C22 * (2.0 * zz - xx - yy)
    out[7] = C23 * x * z
    out[8] = C24 * (xx - yy)
    out[9] = C30 * y * (3.0 * xx - yy)
    out[10] = C31 * x * y * z
    out[11] = C32 * y * (4.0 * zz - xx - yy)
    out[12] = C33 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
    out[13] = C34 * x * (4.0 * zz - xx - yy)
    out[14] = C35 * z * (xx - yy)
    out[15] = C36 * x * (xx - 3.0 * yy)


@njit(inline="always", cache=True)
def _sh_grad_into(x, y, z, out):
    """d basis_k / d(x, y, z) -> out [3, 16] (polynomials, before normalisation)."""
    xx, yy, zz = x * x, y * y, z * z
    out[:, :] = 0.0
    out[0, 3] = -SH_C1
    out[1, 1] = -SH_C1
    out[2, 2] = SH_C1
    out[0, 4], out[1, 4] = C20 * y, C20 * x
    out[1, 5], out[2, 5] = C21 * z, C21 * y
    out[0, 6], out[1, 6], out[2, 6] = -2.0 * C22 * x, -2.0 * C22 * y, 4.0 * C22 * z
    out[0, 7], out[2, 7] = C23 * z, C23 * x
    out[0, 8], out[1, 8] = 2.0 * C24 * x, -2.0 * C24 * y
    out[0, 9], out[1, 9] = 6.0 * C30 * x * y, C30 * (3.0 * xx - 3.0 * yy)
    out[0, 10], out[1, 10], out[2, 10] = C31 * y * z, C31 * x * z, C31 * x * y
    out[0, 11] = -2.0 * C32 * x * y
    out[1, 11] = C32 * (4.0 * zz - xx - 3.0 * yy)
    out[2, 11] = 8.0 * C32 * y * z
    out[0, 12], out[1, 12] = -6.0 * C33 * x * z, -6.0 * C33 * y * z
    out[2, 12] = C33 * (6.0 * zz - 3.0 * xx - 3.0 * yy)
    out[0, 13] = C34 * (4.0 * zz - 3.0 * xx - yy)
    out[1, 13], out[2, 13] = -2.0 * C34 * x * y, 8.0 * C34 * x * z
    out[0, 14], out[1, 14], out[2, 14] = 2.0 * C35 * x * z, -2.0 * C35 * y * z, C35 * (xx - yy)
    out[0, 15], out[1, 15] = C36 * (3.0 * xx - 3.0 * yy), -6.0 * C36 * x * y


# --------------------------------------------------------------------------- projection
@njit(inline="always", cache=True)
def _rotmat(w, x, y, z):
    return (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
            2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
            2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@njit(parallel=True, cache=True)
def project_fwd(means, log_scales, quats, logits, sh, deg, cam, W, H, packed, rect):
    """EWA projection of every Gaussian (float64 math, float32 outputs).

    Args:
        means [N,3], log_scales [N,3], quats [N,4] (wxyz), logits [N], sh [N,K,3]: float32.
        deg: SH degree used. cam: float64 [23] = R_cw (9, row-major), t_cw (3), centre (3),
            fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg.
        W, H: image size.
    Outputs:
        packed: [N, 12] float32 (u, v, conic a, b, c, opacity, r, g, b, z, ext_x, ext_y).
        rect: [N, 4] int32 tile rectangle (tx0, ty0, tx1, ty1), empty (all 0) when culled.
    """
    n = means.shape[0]
    nk = (deg + 1) * (deg + 1)
    fx, fy, cx, cy = cam[15], cam[16], cam[17], cam[18]
    for c in prange((n + CHUNK - 1) // CHUNK):
        basis = np.empty(16, np.float64)
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            rect[i, 0] = 0
            rect[i, 1] = 0
            rect[i, 2] = 0
            rect[i, 3] = 0
            mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            px = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[9]
            py = cam[3] * mx + cam[4] * my + cam[5] * mz + cam[10]
            pz = cam[6] * mx + cam[7] * my + cam[8] * mz + cam[11]
            if not pz > NEAR:
                continue
            op = 1.0 / (1.0 + math.exp(-np.float64(logits[i])))
            if op < ALPHA_MIN64:
                continue
            # Jacobian J (2x3; J01 = J10 = 0) with x/z clamped to the widened frustum
            rz = 1.0 / pz
            rx = min(max(px * rz, -cam[20]), cam[19])
            ry = min(max(py * rz, -cam[22]), cam[21])
            j00, j02 = fx * rz, -fx * rx * rz
            j11, j12 = fy * rz, -fy * ry * rz
            # W = J R_cw
            w00, w01, w02 = j00 * cam[0] + j02 * cam[6], j00 * cam[1] + j02 * cam[7], \
                j00 * cam[2] + j02 * cam[8]
            w10, w11, w12 = j11 * cam[3] + j12 * cam[6], j11 * cam[4] + j12 * cam[7], \
                j11 * cam[5] + j12 * cam[8]
            qw, qx, qy, qz = (np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                              np.float64(quats[i, 2]), np.float64(quats[i, 3]))
            qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            r = _rotmat(qw / qn, qx / qn, qy / qn, qz / qn)
            s0 = math.exp(np.float64(log_scales[i, 0]))
            s1 = math.exp(np.float64(log_scales[i, 1]))
            s2 = math.exp(np.float64(log_scales[i, 2]))
            # T = W M, M = R diag(s); cov2d = T T^T + lowpass
            t00 = (w00 * r[0] + w01 * r[3] + w02 * r[6]) * s0
            t01 = (w00 * r[1] + w01 * r[4] + w02 * r[7]) * s1
            t02 = (w00 * r[2] + w01 * r[5] + w02 * r[8]) * s2
            t10 = (w10 * r[0] + w11 * r[3] + w12 * r[6]) * s0
            t11 = (w10 * r[1] + w11 * r[4] + w12 * r[7]) * s1
            t12 = (w10 * r[2] + w11 * r[5] + w12 * r[8]) * s2
            ca = t00 * t00 + t01 * t01 + t02 * t02 + LOWPASS
            cb = t00 * t10 + t01 * t11 + t02 * t12
            cc = t10 * t10 + t11 * t11 + t12 * t12 + LOWPASS
            det = ca * cc - cb * cb
            if not det > 0.0:
                continue
            u = fx * px * rz + cx
            v = fy * py * rz + cy
            # extent: 3-sigma ellipse, tightened where alpha would fall below 1/255 anyway
            pc = min(POWER_MAX64, math.log(op / ALPHA_MIN64))
            ex = math.sqrt(2.0 * pc * ca) * (1.0 + 1e-4) + 1e-3
            ey = math.sqrt(2.0 * pc * cc) * (1.0 + 1e-4) + 1e-3
            x0 = max(math.ceil(u - ex - 0.5), 0.0)
            x1 = min(math.floor(u + ex - 0.5), W - 1.0)
            y0 = max(math.ceil(v - ey - 0.5), 0.0)
            y1 = min(math.floor(v + ey - 0.5), H - 1.0)
            if x0 > x1 or y0 > y1:
                continue
            # view-dependent colour from SH in direction (mean - camera centre)
            dx, dy, dz = mx - cam[12], my - cam[13], mz - cam[14]
            dn = math.sqrt(dx * dx + dy * dy + dz * dz)
            dn = dn if dn > 0.0 else 1.0
            _sh_basis_into(dx / dn, dy / dn, dz / dn, basis)
            for ch in range(3):
                col = 0.5
                for k in range(nk):
                    col += basis[k] * np.float64(sh[i, k, ch])
                packed[i, 6 + ch] = max(col, 0.0)
            packed[i, 0] = u
            packed[i, 1] = v
            packed[i, 2] = cc / det
            packed[i, 3] = -cb / det
            packed[i, 4] = ca / det
            packed[i, 5] = op
            packed[i, 9] = pz
            packed[i, 10] = ex
            packed[i, 11] = ey
            rect[i, 0] = int(x0) // TILE
            rect[i, 1] = int(y0) // TILE
            rect[i, 2] = int(x1) // TILE + 1
            rect[i, 3] = int(y1) // TILE + 1


@njit(parallel=True, cache=True)
def gather_rows(src, order):
    """``src[order]`` for a 2D array, in parallel."""
    m, k = order.shape[0], src.shape[1]
    out = np.empty((m, k), src.dtype)
    for r in prange(m):
        i = order[r]
        for q in range(k):
            out[r, q] = src[i, q]
    return out


BIN_CHUNKS = 32  # fixed number of rank chunks: the binning result never depends on threads
# Margins of the exact tile test (float64 on the float32 records) over the blend's float32
# decisions: a pair or row is dropped only where every pixel centre is clearly outside.
TEST_REL = 1e-3
TEST_ABS = 1e-2
ROW_PAD = 1e-3


@njit(cache=True)
def _ymax_at(a, b, c, pc, dx):
    """Largest dy with 0.5 (a dx^2 + c dy^2) + b dx dy <= pc at this dx; -inf if none."""
    disc = b * b * dx * dx - c * (a * dx * dx - 2.0 * pc)
    if disc < 0.0:
        return -math.inf
    return (-b * dx + math.sqrt(disc)) / c


@njit(cache=True)
def _ellipse(rec):
    """Per-Gaussian constants of the exact tile test: ``(ok, pc, dy_top, dx_top)``.

    ``pc``: the blend's power cut ``min(4.5, ln(255 opacity))`` widened by the ``TEST_*``
    margins; ``(dx_top, dy_top)``: the ellipse's topmost point relative to its centre (the 2D
    covariance S is the conic's inverse: dy_top = sqrt(2 pc S_yy), dx_top = S_xy / S_yy dy_top).
    ``ok`` is False for a conic that float32 rounding left indefinite (then boxes are kept).
    """
    a, b, c = np.float64(rec[2]), np.float64(rec[3]), np.float64(rec[4])
    det = a * c - b * b
    if not (det > 0.0 and a > 0.0 and c > 0.0):
        return False, 0.0, 0.0, 0.0
    pc = min(POWER_MAX64, math.log(np.float64(rec[5]) / ALPHA_MIN64))
    pc = pc * (1.0 + TEST_REL) + TEST_ABS
    dy_top = math.sqrt(2.0 * pc * a / det)
    return True, pc, dy_top, -b / a * dy_top


@njit(cache=True)
def _tile_rows_of(rec, ok, pc, dy_top, dx_top, single, tx, ty, y_end):
    """:func:`_tile_rows` with the per-Gaussian constants of :func:`_ellipse` given."""
    v = np.float64(rec[1])
    y0 = ty * TILE
    ey = np.float64(rec[11])
    lo_box = max(np.int64(math.ceil(v - ey - 0.5)), y0)
    hi_box = min(np.int64(math.floor(v + ey - 0.5)) + 1, y_end)
    if single or not ok:
        return lo_box, hi_box
    u = np.float64(rec[0])
    a, b, c = np.float64(rec[2]), np.float64(rec[3]), np.float64(rec[4])
    x0 = tx * TILE
    dlo, dhi = x0 + 0.5 - u, x0 + TILE - 0.5 - u
    elo, ehi = y0 + 0.5 - v, y0 + TILE - 0.5 - v
    # minimum of the quadratic form over the rectangle [dlo, dhi] x [elo, ehi]
    if not (dlo <= 0.0 <= dhi and elo <= 0.0 <= ehi):
        best = math.inf
        for e in range(4):
            if e < 2:
                dx = dlo if e == 0 else dhi
                dy = min(max(-b * dx / c, elo), ehi)
            else:
                dy = elo if e == 2 else ehi
                dx = min(max(-b * dy / a, dlo), dhi)
            best = min(best, 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy)
        if best > pc:
            return y0, y0
    # rows: the ellipse's dy range over the strip dx in [dlo, dhi]. The upper boundary is
    # concave with its maximum at dx_top, so off the strip the maximum is at the nearer edge;
    # the ellipse is point-symmetric, so the lower boundary mirrors the upper one.
    if dlo <= dx_top <= dhi:
        top = dy_top
    else:
        top = max(_ymax_at(a, b, c, pc, dlo), _ymax_at(a, b, c, pc, dhi))
    if dlo <= -dx_top <= dhi:
        bot = -dy_top
    else:
        bot = -max(_ymax_at(a, b, c, pc, -dlo), _ymax_at(a, b, c, pc, -dhi))
    if not (top >= bot):
        return y0, y0
    lo = max(np.int64(math.ceil(v + bot - 0.5 - ROW_PAD)), lo_box)
    hi = min(np.int64(math.floor(v + top - 0.5 + ROW_PAD)) + 1, hi_box)
    return lo, hi


@njit(cache=True)
def _tile_rows(rec, single, tx, ty, y_end):
    """Rows ``[lo, hi)`` of tile (tx, ty) whose pixel centres can lie in the Gaussian's blend
    ellipse ``power <= min(4.5, ln(255 opacity))``; ``hi <= lo`` when the tile is missed.

    The tile rectangle of ``project_fwd`` is the ellipse's bounding box, so for a tilted or
    elongated Gaussian many of its tiles (about a fifth of all pairs in trained scenes) see
    no pixel of it. Here the minimum of the quadratic form over the tile's pixel-centre
    rectangle decides whether the tile is touched, and the ellipse's extent over the tile's
    column strip bounds its rows. Both are conservative (``TEST_*`` margins), so every pixel
    the blend would composite is kept: the output and gradients are unchanged, only the
    pairs and rows that contribute nothing are skipped. ``single``: the bounding box is one
    tile; the rows then come from the box alone.
    """
    ok, pc, dy_top, dx_top = _ellipse(rec)
    return _tile_rows_of(rec, ok, pc, dy_top, dx_top, single, tx, ty, y_end)


@njit(parallel=True, cache=True)
def bin_tiles(rect, packed, tiles_x, n_tiles, height, exact):
    """Counting sort of Gaussian-tile pairs into per-tile, depth-sorted lists (parallel).

    A pair is kept only where the Gaussian's ellipse reaches a pixel centre of the tile
    (``_tile_rows``, evaluated once per bounding-box tile and remembered for the scatter).
    The ranks are cut into ``BIN_CHUNKS`` contiguous chunks; each chunk counts its pairs per
    tile, a prefix sum over (tile, chunk) gives every chunk its own write cursor per tile, and
    the chunks then scatter in parallel. Within a tile, pairs stay in rank (= depth) order.

    Args:
        rect: [M, 4] int32 tile rectangles of the visible Gaussians, front to back.
        packed: [M, 12] float32 their blend records, same order.
        height: image height in pixels (rows beyond it are never blended).
        exact: False keeps every bounding-box tile with the box's rows (the binning before
            the exact test; same output, more pairs: kept for measurements of the old trainer).
    Returns:
        tile_off [n_tiles + 1] int64: tile t owns pairs ``tile_off[t]:tile_off[t + 1]``;
        g_off [M + 1] int64 and pair_dst [E] int64: the pair at tile-major position j is
        the ``pair_dst[j]``-th pair in Gaussian-major order, where the pairs of rank r occupy
        ``g_off[r]:g_off[r + 1]`` (the backward writes per-pair gradients there, so that the
        per-Gaussian sums read contiguous memory);
        records [E, 12] float32: the blend record of every pair, tile-major, with columns 10
        and 11 replaced by the pair's first and one-past-last pixel row. The blend kernels
        stream through these instead of gathering ``packed[rank]``, whose scattered reads (one
        cache miss per pair) cost more than all the blending arithmetic.
    """
    m = rect.shape[0]
    csize = (m + BIN_CHUNKS - 1) // BIN_CHUNKS
    box_off = np.zeros(m + 1, np.int64)
    if exact:
        for r in range(m):
            box_off[r + 1] = box_off[r] + (rect[r, 2] - rect[r, 0]) * (rect[r, 3] - rect[r, 1])
    rows = np.empty((box_off[m], 2), np.int32)  # [lo, hi) of every bounding-box tile
    counts = np.zeros((BIN_CHUNKS, n_tiles), np.int64)
    g_cnt = np.zeros(m, np.int64)
    for ch in prange(BIN_CHUNKS):
        for r in range(ch * csize, min(m, (ch + 1) * csize)):
            tx0, ty0, tx1, ty1 = rect[r, 0], rect[r, 1], rect[r, 2], rect[r, 3]
            if not exact:  # every bounding-box tile
                g_cnt[r] = (tx1 - tx0) * (ty1 - ty0)
                for ty in range(ty0, ty1):
                    for tx in range(tx0, tx1):
                        counts[ch, ty * tiles_x + tx] += 1
                continue
            single = (tx1 - tx0) * (ty1 - ty0) == 1
            ok, pc, dy_top, dx_top = (False, 0.0, 0.0, 0.0) if single else _ellipse(packed[r])
            b = box_off[r]
            for ty in range(ty0, ty1):
                y_end = min((ty + 1) * TILE, height)
                for tx in range(tx0, tx1):
                    lo, hi = _tile_rows_of(packed[r], ok, pc, dy_top, dx_top, single, tx, ty,
                                           y_end)
                    rows[b, 0] = lo
                    rows[b, 1] = hi
                    b += 1
                    if hi > lo:
                        counts[ch, ty * tiles_x + tx] += 1
                        g_cnt[r] += 1
    tile_off = np.zeros(n_tiles + 1, np.int64)
    cursors = np.empty((BIN_CHUNKS, n_tiles), np.int64)
    run = 0
    for t in range(n_tiles):
        tile_off[t] = run
        for ch in range(BIN_CHUNKS):
            cursors[ch, t] = run
            run += counts[ch, t]
    tile_off[n_tiles] = run
    g_off = np.zeros(m + 1, np.int64)
    for r in range(m):
        g_off[r + 1] = g_off[r] + g_cnt[r]
    pair_dst = np.empty(run, np.int64)
    records = np.empty((run, NPACK), np.float32)
    for ch in prange(BIN_CHUNKS):
        for r in range(ch * csize, min(m, (ch + 1) * csize)):
            k = g_off[r]
            b = box_off[r]
            for ty in range(rect[r, 1], rect[r, 3]):
                y_end = min((ty + 1) * TILE, height)
                for tx in range(rect[r, 0], rect[r, 2]):
                    if exact:
                        lo, hi = rows[b, 0], rows[b, 1]
                        b += 1
                        if hi <= lo:
                            continue
                    else:
                        lo, hi = _tile_rows_of(packed[r], False, 0.0, 0.0, 0.0, True, tx, ty,
                                               y_end)
                    t = ty * tiles_x + tx
                    j = cursors[ch, t]
                    pair_dst[j] = k
                    for q in range(NPACK - 2):
                        records[j, q] = packed[r, q]
                    records[j, NPACK - 2] = np.float32(lo)
                    records[j, NPACK - 1] = np.float32(hi)
                    cursors[ch, t] = j + 1
                    k += 1
    return tile_off, g_off, pair_dst, records


# --------------------------------------------------------------------------- blending
# Per-tile state lives in ONE flat float32 array with fixed offsets and is indexed with
# unsigned integers: LLVM then vectorises the 16-lane loops (separate arrays need run-time
# alias checks it gives up on; signed indices carry numba's negative-index wraparound; integer
# reductions in the lane loop also block vectorisation, so finished pixels are counted by a
# periodic scan instead).
NPX = TILE * TILE
S_T, S_C0, S_C1, S_C2, S_D, S_A, S_LAST, S_DONE = [np.uint64(i * NPX) for i in range(8)]
N_STATE_FWD = 8
B_T, B_SG, B_G0, B_G1, B_G2, B_GD, B_DREF, B_K, B_LAST = [np.uint64(i * NPX) for i in range(9)]
N_STATE_BWD = 9
DONE_CHECK = 16  # scan for a finished tile every DONE_CHECK list entries
U16 = np.uint64(TILE)


@njit(parallel=True, cache=True)
def blend_fwd(records, tile_off, tile_order, W, H, tiles_x, bg,
              out_rgb, out_depth, out_alpha, out_t, out_last):
    """Front-to-back compositing per 16x16 tile (parallel over tiles).

    Args:
        records: [E, 12] float32 per-tile, depth-sorted blend records (``bin_tiles``).
        tile_off: [T + 1] per-tile list offsets (``bin_tiles``).
        tile_order: [T] int64 tiles in processing order (heaviest first, for balance).
        bg: [3] float32 background.
    Outputs:
        out_rgb [H,W,3], out_depth [H,W], out_alpha [H,W] (sum of weights = 1 - T),
        out_t [H,W] (final T), out_last [H,W] int32 (list entries consumed, i.e. index of the
        last contributor + 1).
    """
    n_tiles = tile_order.shape[0]
    for it in prange(n_tiles):
        t = tile_order[it]
        ty, tx = t // tiles_x, t % tiles_x
        x0, y0 = tx * TILE, ty * TILE
        y_end = min(y0 + TILE, H)
        nx = min(x0 + TILE, W) - x0
        st = np.zeros(N_STATE_FWD * NPX, np.float32)
        xs = np.empty(TILE, np.float32)
        for q in range(NPX):
            st[S_T + np.uint64(q)] = F1
        for k in range(TILE):
            xs[k] = np.float32(x0 + k) + FHALF
            if k >= nx:  # lanes beyond the right border never contribute
                for row in range(TILE):
                    st[S_DONE + np.uint64(row * TILE + k)] = F1
        for row in range(y_end - y0, TILE):  # rows beyond the bottom border
            for k in range(TILE):
                st[S_DONE + np.uint64(row * TILE + k)] = F1
        start, end = tile_off[t], tile_off[t + 1]
        for j in range(start, end):
            if (j - start) % DONE_CHECK == 0 and j > start:
                n_done = F0
                for q in range(NPX):
                    n_done += st[S_DONE + np.uint64(q)]
                if n_done >= np.float32(NPX):
                    break
            u, v = records[j, 0], records[j, 1]
            ca, cb, cc, op = records[j, 2], records[j, 3], records[j, 4], records[j, 5]
            r, gr, b, z = records[j, 6], records[j, 7], records[j, 8], records[j, 9]
            lo, hi = np.int64(records[j, 10]), np.int64(records[j, 11])
            jn = np.float32(j - start + 1)
            for row in range(lo, hi):
                dy = np.float32(row) + FHALF - v
                base = np.uint64((row - y0) * TILE)
                for k in range(TILE):
                    q = base + np.uint64(k)
                    dx = xs[k] - u
                    power = FHALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    raw = op * _exp_neg(power)
                    alpha = min(raw, F_ALPHA_MAX)
                    ok = (power <= F_POWER_MAX) & (raw >= F_ALPHA_MIN) & (st[S_DONE + q] == F0)
                    t_old = st[S_T + q]
                    t_new = t_old * (F1 - alpha)
                    stop = ok & (t_new < F_T_MIN)
                    use = ok & (t_new >= F_T_MIN)
                    w = alpha * t_old if use else F0
                    st[S_C0 + q] += w * r
                    st[S_C1 + q] += w * gr
                    st[S_C2 + q] += w * b
                    st[S_D + q] += w * z
                    st[S_A + q] += w
                    st[S_T + q] = t_new if use else t_old
                    st[S_LAST + q] = jn if use else st[S_LAST + q]
                    st[S_DONE + q] = F1 if stop else st[S_DONE + q]
        for row in range(y0, y_end):
            for k in range(nx):
                q = np.uint64((row - y0) * TILE + k)
                x = x0 + k
                tq = st[S_T + q]
                out_rgb[row, x, 0] = st[S_C0 + q] + tq * bg[0]
                out_rgb[row, x, 1] = st[S_C1 + q] + tq * bg[1]
                out_rgb[row, x, 2] = st[S_C2 + q] + tq * bg[2]
                a = st[S_A + q]
                out_alpha[row, x] = a
                out_depth[row, x] = st[S_D + q] / a if a >= F_ALPHA_DEPTH_MIN else F0
                out_t[row, x] = tq
                out_last[row, x] = np.int32(st[S_LAST + q])


@njit(parallel=True, cache=True)
def blend_bwd(records, tile_off, pair_dst, tile_order, W, H, tiles_x, bg,
              out_depth, out_alpha, out_t, out_last, g_rgb, g_depth, g_alpha, pair_grad):
    """Backward of ``blend_fwd``: one gradient record per Gaussian-tile pair.

    Walks every tile list back to front from the last contributor; T before a Gaussian is
    recovered as T / (1 - alpha), the (colour, depth) behind it by the running sum of 3DGS,
    dotted with the upstream gradient so that one scalar per pixel suffices. Depth enters as
    z_i - D (D the pixel's normalised depth): then the quotient rule's d/d(alpha_acc) term
    vanishes instead of cancelling two large 1/alpha terms in float32.

    Args:
        g_rgb [H,W,3], g_depth [H,W], g_alpha [H,W]: float32 upstream gradients.
        pair_dst: [E] from ``bin_tiles``.
    Outputs:
        pair_grad: [E, 10] float32, d loss / d (u, v, conic a, b, c, opacity, r, g, b, z)
            for each Gaussian-tile pair, in Gaussian-major order (row ``pair_dst[j]``).
    """
    n_tiles = tile_order.shape[0]
    for it in prange(n_tiles):
        t = tile_order[it]
        ty, tx = t // tiles_x, t % tiles_x
        x0, y0 = tx * TILE, ty * TILE
        y_end = min(y0 + TILE, H)
        nx = min(x0 + TILE, W) - x0
        st = np.zeros(N_STATE_BWD * NPX, np.float32)
        acc = np.zeros(NPAR * TILE, np.float32)
        xs = np.empty(TILE, np.float32)
        for k in range(TILE):
            xs[k] = np.float32(x0 + k) + FHALF
        max_last = 0
        for row in range(y0, y_end):
            for k in range(nx):
                q = np.uint64((row - y0) * TILE + k)
                x = x0 + k
                tq = out_t[row, x]
                a = out_alpha[row, x]
                gr0, gr1, gr2 = g_rgb[row, x, 0], g_rgb[row, x, 1], g_rgb[row, x, 2]
                if a >= F_ALPHA_DEPTH_MIN:
                    st[B_GD + q] = g_depth[row, x] / a
                    st[B_DREF + q] = out_depth[row, x]
                st[B_T + q] = tq
                st[B_G0 + q] = gr0
                st[B_G1 + q] = gr1
                st[B_G2 + q] = gr2
                st[B_K + q] = tq * (g_alpha[row, x] - (bg[0] * gr0 + bg[1] * gr1 + bg[2] * gr2))
                st[B_LAST + q] = np.float32(out_last[row, x])
                max_last = max(max_last, out_last[row, x])
        start = tile_off[t]
        for jj in range(max_last - 1, -1, -1):
            j = start + jj
            u, v = records[j, 0], records[j, 1]
            ca, cb, cc, op = records[j, 2], records[j, 3], records[j, 4], records[j, 5]
            r, gr, b, z = records[j, 6], records[j, 7], records[j, 8], records[j, 9]
            lo, hi = np.int64(records[j, 10]), np.int64(records[j, 11])
            jf = np.float32(jj)
            for q in range(NPAR * TILE):
                acc[q] = F0
            for row in range(lo, hi):
                dy = np.float32(row) + FHALF - v
                base = np.uint64((row - y0) * TILE)
                for k in range(TILE):
                    q = base + np.uint64(k)
                    kk = np.uint64(k)
                    dx = xs[k] - u
                    power = FHALF * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    gauss = _exp_neg(power)
                    raw = op * gauss
                    alpha = min(raw, F_ALPHA_MAX)
                    act = (power <= F_POWER_MAX) & (raw >= F_ALPHA_MIN) & (jf < st[B_LAST + q])
                    oma = F1 - alpha
                    inv_oma = F1 / oma
                    t_before = st[B_T + q] * inv_oma
                    g0, g1, g2, gdn = st[B_G0 + q], st[B_G1 + q], st[B_G2 + q], st[B_GD + q]
                    fg = r * g0 + gr * g1 + b * g2 + (z - st[B_DREF + q]) * gdn
                    sg = st[B_SG + q]
                    dl_dalpha = t_before * (fg - sg) + st[B_K + q] * inv_oma
                    w = alpha * t_before if act else F0
                    dl_draw = dl_dalpha if (act & (raw <= F_ALPHA_MAX)) else F0
                    acc[kk] += w * g0
                    acc[U16 + kk] += w * g1
                    acc[np.uint64(2 * TILE) + kk] += w * g2
                    acc[np.uint64(3 * TILE) + kk] += w * gdn
                    acc[np.uint64(4 * TILE) + kk] += dl_draw * gauss
                    dpow = -dl_draw * raw  # d loss / d power
                    acc[np.uint64(5 * TILE) + kk] -= dpow * (ca * dx + cb * dy)
                    acc[np.uint64(6 * TILE) + kk] -= dpow * (cb * dx + cc * dy)
                    acc[np.uint64(7 * TILE) + kk] += dpow * FHALF * dx * dx
                    acc[np.uint64(8 * TILE) + kk] += dpow * dx * dy
                    acc[np.uint64(9 * TILE) + kk] += dpow * FHALF * dy * dy
                    st[B_SG + q] = alpha * fg + oma * sg if act else sg
                    st[B_T + q] = t_before if act else st[B_T + q]
            # acc rows: r, g, b, z, opacity, u, v, a, b, c -> pair_grad columns
            dst = pair_dst[j]
            for p in range(NPAR):
                s = F0
                for k in range(TILE):
                    s += acc[p * TILE + k]
                pair_grad[dst, _ACC_TO_PAIR[p]] = s


_ACC_TO_PAIR = np.array([6, 7, 8, 9, 5, 0, 1, 2, 3, 4], np.int64)


@njit(parallel=True, cache=True)
def reduce_pairs(pair_grad, g_off, order, g2d):
    """Sum the Gaussian-major pair gradients per Gaussian (float64, fixed order).

    Args:
        pair_grad: [E, 10] from ``blend_bwd``; g_off [M + 1], order [M] from ``bin_tiles``.
    Outputs:
        g2d: [N, 10] float64, zero-initialised by the caller; row ``order[r]`` receives the
            sum of rows ``g_off[r]:g_off[r + 1]``.
    """
    m = order.shape[0]
    for r in prange(m):
        i = order[r]
        for p in range(NPAR):
            acc = 0.0
            for e in range(g_off[r], g_off[r + 1]):
                acc += pair_grad[e, p]
            g2d[i, p] = acc


@njit(parallel=True, cache=True)
def project_bwd(means, log_scales, quats, logits, sh, deg, cam, visible, g2d,
                g_means, g_log_scales, g_quats, g_logits, g_sh):
    """Backward of ``project_fwd`` (float64 math) for the visible Gaussians.

    Args:
        visible: [N] bool, Gaussians that reached at least one tile.
        g2d: [N, 10] float64 d loss / d (u, v, conic a, b, c, opacity, r, g, b, z).
    Outputs (zero-initialised by the caller; rows of culled Gaussians stay zero):
        g_means [N,3], g_log_scales [N,3], g_quats [N,4], g_logits [N], g_sh [N,K,3].
    """
    n = visible.shape[0]
    nk = (deg + 1) * (deg + 1)
    fx, fy = cam[15], cam[16]
    for c in prange((n + CHUNK - 1) // CHUNK):
        basis = np.empty(16, np.float64)
        dbasis = np.empty((3, 16), np.float64)
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            if not visible[i]:
                continue
            gu, gv, gA, gB, gC = g2d[i, 0], g2d[i, 1], g2d[i, 2], g2d[i, 3], g2d[i, 4]
            gop, gc0, gc1, gc2, gz = g2d[i, 5], g2d[i, 6], g2d[i, 7], g2d[i, 8], g2d[i, 9]
            # ---- recompute the forward quantities
            mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
            px = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[9]
            py = cam[3] * mx + cam[4] * my + cam[5] * mz + cam[10]
            pz = cam[6] * mx + cam[7] * my + cam[8] * mz + cam[11]
            op = 1.0 / (1.0 + math.exp(-np.float64(logits[i])))
            rz = 1.0 / pz
            rxu, ryu = px * rz, py * rz
            rx = min(max(rxu, -cam[20]), cam[19])
            ry = min(max(ryu, -cam[22]), cam[21])
            j00, j02 = fx * rz, -fx * rx * rz
            j11, j12 = fy * rz, -fy * ry * rz
            w00, w01, w02 = j00 * cam[0] + j02 * cam[6], j00 * cam[1] + j02 * cam[7], \
                j00 * cam[2] + j02 * cam[8]
            w10, w11, w12 = j11 * cam[3] + j12 * cam[6], j11 * cam[4] + j12 * cam[7], \
                j11 * cam[5] + j12 * cam[8]
            qw, qx, qy, qz = (np.float64(quats[i, 0]), np.float64(quats[i, 1]),
                              np.float64(quats[i, 2]), np.float64(quats[i, 3]))
            qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            nw, nx_, ny, nz = qw / qn, qx / qn, qy / qn, qz / qn
            r = _rotmat(nw, nx_, ny, nz)
            s0 = math.exp(np.float64(log_scales[i, 0]))
            s1 = math.exp(np.float64(log_scales[i, 1]))
            s2 = math.exp(np.float64(log_scales[i, 2]))
            # Wr = W R (2x3); T = Wr diag(s)
            a00 = w00 * r[0] + w01 * r[3] + w02 * r[6]
            a01 = w00 * r[1] + w01 * r[4] + w02 * r[7]
            a02 = w00 * r[2] + w01 * r[5] + w02 * r[8]
            a10 = w10 * r[0] + w11 * r[3] + w12 * r[6]
            a11 = w10 * r[1] + w11 * r[4] + w12 * r[7]
            a12 = w10 * r[2] + w11 * r[5] + w12 * r[8]
            t00, t01, t02 = a00 * s0, a01 * s1, a02 * s2
            t10, t11, t12 = a10 * s0, a11 * s1, a12 * s2
            ca = t00 * t00 + t01 * t01 + t02 * t02 + LOWPASS
            cb = t00 * t10 + t01 * t11 + t02 * t12
            cc = t10 * t10 + t11 * t11 + t12 * t12 + LOWPASS
            det = ca * cc - cb * cb
            qa, qb, qc = cc / det, -cb / det, ca / det  # conic = inverse covariance
            # ---- conic -> covariance: dL/dS = -Q G Q with G = [[gA, gB/2], [gB/2, gC]]
            hb = 0.5 * gB
            m00 = qa * gA + qb * hb
            m01 = qa * hb + qb * gC
            m10 = qb * gA + qc * hb
            m11 = qb * hb + qc * gC
            gs00 = -(m00 * qa + m01 * qb)
            gs01 = -(m00 * qb + m01 * qc)
            gs11 = -(m10 * qb + m11 * qc)
            # ---- cov2d = T T^T: dL/dT = 2 G_S T
            d00 = 2.0 * (gs00 * t00 + gs01 * t10)
            d01 = 2.0 * (gs00 * t01 + gs01 * t11)
            d02 = 2.0 * (gs00 * t02 + gs01 * t12)
            d10 = 2.0 * (gs01 * t00 + gs11 * t10)
            d11 = 2.0 * (gs01 * t01 + gs11 * t11)
            d12 = 2.0 * (gs01 * t02 + gs11 * t12)
            # scales: T_ij = Wr_ij s_j
            g_log_scales[i, 0] = (d00 * a00 + d10 * a10) * s0
            g_log_scales[i, 1] = (d01 * a01 + d11 * a11) * s1
            g_log_scales[i, 2] = (d02 * a02 + d12 * a12) * s2
            # dL/dWr = dT diag(s); Wr = W R -> dL/dR = W^T dWr, dL/dW = dWr R^T
            e00, e01, e02 = d00 * s0, d01 * s1, d02 * s2
            e10, e11, e12 = d10 * s0, d11 * s1, d12 * s2
            gr0 = w00 * e00 + w10 * e10
            gr1 = w00 * e01 + w10 * e11
            gr2 = w00 * e02 + w10 * e12
            gr3 = w01 * e00 + w11 * e10
            gr4 = w01 * e01 + w11 * e11
            gr5 = w01 * e02 + w11 * e12
            gr6 = w02 * e00 + w12 * e10
            gr7 = w02 * e01 + w12 * e11
            gr8 = w02 * e02 + w12 * e12
            gw00 = e00 * r[0] + e01 * r[1] + e02 * r[2]
            gw01 = e00 * r[3] + e01 * r[4] + e02 * r[5]
            gw02 = e00 * r[6] + e01 * r[7] + e02 * r[8]
            gw10 = e10 * r[0] + e11 * r[1] + e12 * r[2]
            gw11 = e10 * r[3] + e11 * r[4] + e12 * r[5]
            gw12 = e10 * r[6] + e11 * r[7] + e12 * r[8]
            # rotation matrix from the normalised quaternion
            gqw = 2.0 * (-nz * gr1 + ny * gr2 + nz * gr3 - nx_ * gr5 - ny * gr6 + nx_ * gr7)
            gqx = 2.0 * (ny * gr1 + nz * gr2 + ny * gr3 - 2.0 * nx_ * gr4 - nw * gr5
                         + nz * gr6 + nw * gr7 - 2.0 * nx_ * gr8)
            gqy = 2.0 * (-2.0 * ny * gr0 + nx_ * gr1 + nw * gr2 + nx_ * gr3 + nz * gr5
                         - nw * gr6 + nz * gr7 - 2.0 * ny * gr8)
            gqz = 2.0 * (-2.0 * nz * gr0 - nw * gr1 + nx_ * gr2 + nw * gr3 - 2.0 * nz * gr4
                         + ny * gr5 + nx_ * gr6 + ny * gr7)
            dot = nw * gqw + nx_ * gqx + ny * gqy + nz * gqz
            g_quats[i, 0] = (gqw - nw * dot) / qn
            g_quats[i, 1] = (gqx - nx_ * dot) / qn
            g_quats[i, 2] = (gqy - ny * dot) / qn
            g_quats[i, 3] = (gqz - nz * dot) / qn
            # W = J R_cw -> dL/dJ = dW R_cw^T (only J00, J02, J11, J12 are non-zero)
            gj00 = gw00 * cam[0] + gw01 * cam[1] + gw02 * cam[2]
            gj02 = gw00 * cam[6] + gw01 * cam[7] + gw02 * cam[8]
            gj11 = gw10 * cam[3] + gw11 * cam[4] + gw12 * cam[5]
            gj12 = gw10 * cam[6] + gw11 * cam[7] + gw12 * cam[8]
            gpx = gu * fx * rz
            gpy = gv * fy * rz
            gpz = gz - (gu * fx * px + gv * fy * py) * rz * rz
            gpz += -(gj00 * j00 + gj11 * j11 + gj02 * j02 + gj12 * j12) * rz
            g_rx = -gj02 * fx * rz
            g_ry = -gj12 * fy * rz
            if -cam[20] <= rxu <= cam[19]:
                gpx += g_rx * rz
                gpz -= g_rx * rxu * rz
            if -cam[22] <= ryu <= cam[21]:
                gpy += g_ry * rz
                gpz -= g_ry * ryu * rz
            # p = R_cw m + t
            gmx = cam[0] * gpx + cam[3] * gpy + cam[6] * gpz
            gmy = cam[1] * gpx + cam[4] * gpy + cam[7] * gpz
            gmz = cam[2] * gpx + cam[5] * gpy + cam[8] * gpz
            # opacity
            g_logits[i] = gop * op * (1.0 - op)
            # colour: SH in the normalised direction (mean - centre)
            dx, dy, dz = mx - cam[12], my - cam[13], mz - cam[14]
            dn = math.sqrt(dx * dx + dy * dy + dz * dz)
            dn = dn if dn > 0.0 else 1.0
            ux, uy, uz = dx / dn, dy / dn, dz / dn
            _sh_basis_into(ux, uy, uz, basis)
            _sh_grad_into(ux, uy, uz, dbasis)
            gux, guy, guz = 0.0, 0.0, 0.0
            for ch in range(3):
                col = 0.5
                for k in range(nk):
                    col += basis[k] * np.float64(sh[i, k, ch])
                if col < 0.0:
                    continue
                gcol = gc0 if ch == 0 else (gc1 if ch == 1 else gc2)
                for k in range(nk):
                    g_sh[i, k, ch] = basis[k] * gcol
                    shk = np.float64(sh[i, k, ch]) * gcol
                    gux += dbasis[0, k] * shk
                    guy += dbasis[1, k] * shk
                    guz += dbasis[2, k] * shk
            udot = ux * gux + uy * guy + uz * guz
            g_means[i, 0] = gmx + (gux - ux * udot) / dn
            g_means[i, 1] = gmy + (guy - uy * udot) / dn
            g_means[i, 2] = gmz + (guz - uz * udot) / dn
