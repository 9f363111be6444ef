"""Per-view trust: scores of a rendered free view that predict its true error (issue 19).

The stage-7 scores (BRISQUE, black ratio, depth validity) look at the render alone and barely
rank free views by their true PSNR (Spearman -0.23 / -0.58 / -0.26 on the sample scene). The
scores here use what the engine knows besides the render: the captured photos, the certainty
grid and the training rays. All are computed on CPU in numpy; each has an obvious-loop
reference in ``tests/freeviews/test_trust.py``.

* **Photometric consistency** (:func:`photometric_consistency`): the nearest overlapping
  training photos (:func:`nearest_training_views`) are warped into the free view through the
  rendered depth (each free-view pixel is lifted to 3D and sampled bilinearly in the photo),
  keeping a pixel only where the point is the training view's first surface (occlusion check:
  its depth in the training camera agrees within ``depth_tol`` with the training view's
  rendered depth there). ``photo_psnr`` is the PSNR between the render and the warped photos
  over the supported pixels (each pixel's squared error averaged over the photos that
  support it), ``photo_support`` the share of pixels with any support.
* **Certainty support** (:func:`certainty_support`): the rendered depth's 3D points are looked
  up in the certainty grid (dilated by one voxel: Gaussian centres sit near, not on, the
  surface). ``certain_share`` = sum(alpha * [C >= high]) / (H W), the share of the view's
  colour that comes from high-certainty voxels; ``beyond_share`` = share of pixels that are
  empty (alpha < ``alpha_min``) or whose point lies outside the box or in a voxel below the
  low threshold, i.e. the view looks beyond the certain region.
* **Geometric sanity** (:func:`depth_edge_share`, :func:`floater_share`,
  :func:`view_angle_deg`): the share of valid pixels at a depth discontinuity (relative jump
  > ``tau`` to a 4-neighbour), the share of pixels that are isolated near-camera blobs (depth
  < ``ratio`` x the median depth of their ``window`` neighbourhood, empty pixels counting as
  far), and the median over pixels of the angle between the free view's ray and the nearest
  training ray through the same 3D point (training cameras that see the point in their
  frustum; 180 when none).

The combination (:func:`predict_psnr`) is a ridge regression on these and the stage-7 scores,
fitted by ``benchmarks/fit_trust.py`` on procedural sample scenes only (never real scenes),
frozen below as constants: it predicts the render's PSNR in dB against the truth.
:func:`loss_weight` turns a predicted PSNR into a loss weight for refine / LVSM training.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from freescale_core.errors import ShapeError
from freescale_core.freeviews.rectify_image import RenderedView, _lift, _project

__all__ = ["TrustScores", "TrustContext", "nearest_training_views", "bilinear_sample",
           "photometric_consistency", "certainty_support", "depth_edge_share",
           "floater_share", "floater_share_median", "lifted_points",
           "view_angle_deg", "trust_features", "predict_psnr",
           "loss_weight", "score_trust", "FEATURES", "TRUST_COLUMNS"]

# --------------------------------------------------------------------------- frozen model
# Fitted by benchmarks/fit_trust.py (ridge on standardised features, sample scenes only);
# see docs/FIDELITY.md "Trust" for the data and the command. NaN features are imputed with
# the mean (a zero after standardisation).
FEATURES = ("photo_psnr", "photo_support", "certain_share", "beyond_share", "depth_edges",
            "floaters", "log_view_angle", "brisque", "black_ratio", "depth_validity",
            "photo_blend", "support_x_psnr", "black_ratio_sq")
_UNSUPPORTED_PSNR = 12.0  # photo_blend: the PSNR assumed where no photo supports a pixel
# Fit: 600 renders (60 feasible candidates each) of 10 sample scenes, seeds 10-17 with 16/12/24
# frames at 128x96 (--quick recon) and seeds 20-21 with 24/36 frames at 192x144 (fast recon);
# ridge alpha 3 by leave-one-scene-out CV (Spearman 0.884, MAE 2.07 dB):
#   python benchmarks/fit_trust.py collect --seeds 10 11 12 13 --views 16 12 24 --out a.jsonl
#   python benchmarks/fit_trust.py collect --seeds 14 15 16 17 --views 16 12 24 --out b.jsonl
#   python benchmarks/fit_trust.py collect --full --seeds 20 21 --views 24 36 --width 192 \
#       --height 144 --out c.jsonl
#   python benchmarks/fit_trust.py fit a.jsonl b.jsonl c.jsonl
_MEAN = np.array([23.36022, 0.601145, 0.392057, 0.515264, 0.049708, 0.00287, 1.750523,
                  0.374502, 0.049371, 0.765536, 16.017709, 14.604996, 0.008634])
_SCALE = np.array([6.90861, 0.271108, 0.17196, 0.190564, 0.049754, 0.004324, 1.184584,
                   0.194935, 0.078721, 0.109482, 2.697605, 7.164401, 0.021769])
_COEF = np.array([1.25662, -4.103081, -0.545621, -1.034798, 0.04957, -0.29318, -0.63484,
                  -0.644419, -4.400435, -0.154277, 0.951811, 4.490156, 2.382133])
_INTERCEPT = 16.941429
_PHOTO_PSNR_CLIP = (5.0, 45.0)

# the columns a trust-scored record carries (views.parquet, FreeViewRecord)
TRUST_COLUMNS = ("photo_psnr", "photo_support", "certain_share", "beyond_share",
                 "depth_edges", "floaters", "view_angle_deg", "pred_psnr")


@dataclass
class TrustScores:
    """The trust scores of one rendered view (see the module docstring); NaN = not computed.
    ``freeviews.run.FreeViewRecord`` extends it, so a record carries these fields once.

    ``pred_psnr`` is :func:`predict_psnr` of the scores and the view's stage-7 scores.
    """

    photo_psnr: float = math.nan
    photo_support: float = math.nan
    certain_share: float = math.nan
    beyond_share: float = math.nan
    depth_edges: float = math.nan
    floaters: float = math.nan
    view_angle_deg: float = math.nan
    pred_psnr: float = math.nan

    def as_dict(self) -> dict:
        return asdict(self)


def _valid(view: RenderedView, alpha_min: float) -> np.ndarray:
    d = np.asarray(view.depth)
    ok = np.isfinite(d) & (d > 0)
    if view.alpha is not None:
        ok &= np.asarray(view.alpha) >= alpha_min
    return ok


def lifted_points(view: RenderedView, alpha_min: float = 0.5) -> np.ndarray:
    """``[H, W, 3]`` world points of the view's pixels at its depth where valid (alpha >=
    ``alpha_min``, finite depth > 0), at camera z = 1 elsewhere: what every geometric trust
    score starts from (:func:`score_trust` lifts once and hands it to each)."""
    return _lift(view, np.where(_valid(view, alpha_min), view.depth, 1.0))


# --------------------------------------------------------------------------- references
def nearest_training_views(view: RenderedView, train_poses: np.ndarray, fx, fy, cx, cy,
                           width, height, k: int = 3, alpha_min: float = 0.5,
                           max_angle_deg: float = 45.0, stride: int = 4,
                           points: np.ndarray | None = None) -> np.ndarray:
    """Training views that see most of the free view's surface from a similar direction.

    Every ``stride``-th valid pixel is lifted with the rendered depth; a training view's score
    is the share of these points that project in front of it, inside its image, with an angle
    at the point between the two rays <= ``max_angle_deg``. Returns up to ``k`` training
    indices with a score > 0, best first (ties: lowest index).

    Args:
        view: the free view (depth, alpha, camera).
        train_poses: ``[T, 4, 4]`` world-from-camera; ``fx .. height``: ``[T]`` intrinsics.
        points: ``[H, W, 3]`` the view's pixels lifted with its depth where valid (1 elsewhere),
            :func:`lifted_points`; computed when None.
    """
    ok = _valid(view, alpha_min)[::stride, ::stride]
    T = len(train_poses)
    if T == 0 or not ok.any():
        return np.zeros(0, np.int64)
    X = (lifted_points(view, alpha_min) if points is None else points)[::stride, ::stride][ok]
    cv = np.asarray(view.world_from_cam, np.float64)[:3, 3]
    a = X - cv
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-300)
    cos_max = math.cos(math.radians(max_angle_deg))
    score = np.zeros(T)
    for t in range(T):
        Pt = np.asarray(train_poses[t], np.float64)
        Xc = (X - Pt[:3, 3]) @ Pt[:3, :3]
        z = Xc[:, 2]
        zs = np.where(z > 1e-9, z, 1.0)
        u = fx[t] * Xc[:, 0] / zs + cx[t]
        v = fy[t] * Xc[:, 1] / zs + cy[t]
        b = X - Pt[:3, 3]
        b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)
        inside = (z > 1e-9) & (u >= 0) & (u < width[t]) & (v >= 0) & (v < height[t])
        score[t] = np.mean(inside & ((a * b).sum(1) >= cos_max))
    order = np.lexsort((np.arange(T), -score))
    return order[score[order] > 0][:k].astype(np.int64)


# --------------------------------------------------------------------------- photometric
def bilinear_sample(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``img [H, W, C]`` at continuous index coordinates ``(x, y)``
    (pixel ``(i, j)``'s centre is ``x = j, y = i``); coordinates are clamped to the image."""
    H, W = img.shape[:2]
    x = np.clip(np.asarray(x, np.float64), 0.0, W - 1.0)
    y = np.clip(np.asarray(y, np.float64), 0.0, H - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(W - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(H - 2, 0))
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    im = np.asarray(img, np.float64)
    top = im[y0, x0] * (1 - fx) + im[y0, x1] * fx
    bot = im[y1, x0] * (1 - fx) + im[y1, x1] * fx
    return top * (1 - fy) + bot * fy


def photometric_consistency(view: RenderedView, refs: list[tuple[np.ndarray, RenderedView]],
                            alpha_min: float = 0.5, depth_tol: float = 0.03,
                            points: np.ndarray | None = None
                            ) -> tuple[float, float, np.ndarray]:
    """Disagreement of a render with the training photos warped into it.

    For each reference ``(photo, ref_render)`` (photo ``[Hr, Wr, 3]`` uint8 or float in
    [0, 1], or ``[Hr, Wr, 4]`` whose 4th channel is the photo's object mask: a pixel is
    supported only where every bilinear tap of its sample is inside the mask; ``ref_render`` the
    training camera with its rendered depth/alpha), each valid
    free-view pixel (alpha >= ``alpha_min``, depth > 0) is lifted with the rendered depth and
    projected into the reference; it is *supported* when it lands in front of the camera,
    inside the photo (pixel centres ``0.5 .. W - 0.5``), and the reference's rendered depth at
    the nearest pixel is valid and within ``depth_tol`` (relative) of the point's depth there
    (the point is the first surface the reference sees). The photo is sampled bilinearly.

    Returns:
        ``(photo_psnr dB, photo_support in [0, 1], err [H, W])``: the PSNR of the render
        against the warped photos over supported pixels (each pixel's squared error, mean
        over channels, averaged over the references that support it), NaN when no pixel is
        supported; the share of the view's pixels with any support; the per-pixel error
        (NaN where unsupported).

    The projection is numpy's (:func:`_project`); the support test, the bilinear sample and
    the error run in one numba pass per reference (:func:`_photo_accumulate`), without the
    photo converted to float64 or ``[N, 3]`` temporaries; bit-identical to
    :func:`photometric_consistency_numpy` (tested). A photo with a mask channel takes the
    numpy path.
    """
    if any(np.asarray(ph).shape[-1] >= 4 for ph, _ in refs):
        return photometric_consistency_numpy(view, refs, alpha_min, depth_tol, points)
    H, W = view.hw
    ok = _valid(view, alpha_min)
    rgb = np.asarray(view.rgb)
    rgb = rgb.astype(np.float64) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float64)
    sse = np.zeros((H, W))
    cnt = np.zeros((H, W))
    X = lifted_points(view, alpha_min) if points is None else points
    for photo, ref in refs:
        ph = np.asarray(photo)
        Hr, Wr = ph.shape[:2]
        if ref.depth is None or np.asarray(ref.depth).shape != (Hr, Wr):
            raise ShapeError("reference depth", getattr(ref.depth, "shape", ()),
                             f"[{Hr}, {Wr}] (the photo's size)")
        # uint8 photos are read as value / 255 per tap (what astype(float64) / 255 gives)
        div = 255.0 if ph.dtype == np.uint8 else 1.0
        if ph.dtype != np.uint8:
            ph = ph.astype(np.float64)
        u, v, z = _project(ref, X)
        _photo_accumulate(np.ascontiguousarray(u, np.float64),
                          np.ascontiguousarray(v, np.float64),
                          np.ascontiguousarray(z, np.float64), ok,
                          np.ascontiguousarray(ref.depth), _valid(ref, alpha_min),
                          np.ascontiguousarray(ph[..., :3]), div, rgb, float(depth_tol),
                          sse, cnt)
    has = cnt > 0
    err = np.where(has, sse / np.maximum(cnt, 1), np.nan)
    if not has.any():
        return math.nan, 0.0, err
    mse = float(err[has].mean())
    return (math.inf if mse <= 0 else -10.0 * math.log10(mse)), float(has.mean()), err


@njit(cache=True, nogil=True)
def _photo_accumulate(u, v, z, ok, d_ref, r_ok, ph, div, rgb, tol, sse, cnt
                      ):  # pragma: no cover - numba
    """One reference of :func:`photometric_consistency`: per free-view pixel with its
    projection ``(u, v, z)`` into the reference, the support test (in front, inside the
    photo, the reference's depth valid and within ``tol``) and, where supported, the squared
    error (mean over channels) of the bilinearly sampled photo (``ph / div``) against
    ``rgb``, added to ``sse`` with ``cnt`` += 1. The operations of
    :func:`photometric_consistency_numpy` / :func:`bilinear_sample` in their order."""
    H, W = ok.shape
    Hr, Wr = ph.shape[0], ph.shape[1]
    C = ph.shape[2]
    xmax, ymax = Wr - 1.0, Hr - 1.0
    x0max, y0max = max(Wr - 2, 0), max(Hr - 2, 0)
    for i in range(H):
        for j in range(W):
            zz = z[i, j]
            uu = u[i, j]
            vv = v[i, j]
            if not (ok[i, j] and zz > 1e-9 and uu >= 0.5 and uu <= Wr - 0.5 and vv >= 0.5
                    and vv <= Hr - 0.5):
                continue
            iy = min(max(int(math.floor(vv)), 0), Hr - 1)
            ix = min(max(int(math.floor(uu)), 0), Wr - 1)
            dr = np.float64(d_ref[iy, ix])
            if not (r_ok[iy, ix] and abs(zz - dr) <= tol * dr):
                continue
            x = min(max(uu - 0.5, 0.0), xmax)
            y = min(max(vv - 0.5, 0.0), ymax)
            x0 = min(int(math.floor(x)), x0max)
            y0 = min(int(math.floor(y)), y0max)
            x1 = min(x0 + 1, Wr - 1)
            y1 = min(y0 + 1, Hr - 1)
            fx = x - x0
            fy = y - y0
            e = 0.0
            for c in range(C):
                top = (np.float64(ph[y0, x0, c]) / div * (1 - fx)
                       + np.float64(ph[y0, x1, c]) / div * fx)
                bot = (np.float64(ph[y1, x0, c]) / div * (1 - fx)
                       + np.float64(ph[y1, x1, c]) / div * fx)
                d = top * (1 - fy) + bot * fy - rgb[i, j, c]
                e += d * d
            sse[i, j] += e / C
            cnt[i, j] += 1


def photometric_consistency_numpy(view: RenderedView, refs: list[tuple[np.ndarray, RenderedView]],
                            alpha_min: float = 0.5, depth_tol: float = 0.03,
                            points: np.ndarray | None = None
                            ) -> tuple[float, float, np.ndarray]:
    """:func:`photometric_consistency` in numpy, reference by reference (the code before
    issue 63's kernel; the reference it is tested against, and the path of masked photos)."""
    H, W = view.hw
    ok = _valid(view, alpha_min)
    rgb = np.asarray(view.rgb)
    rgb = rgb.astype(np.float64) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float64)
    sse = np.zeros((H, W))
    cnt = np.zeros((H, W))
    X = lifted_points(view, alpha_min) if points is None else points
    for photo, ref in refs:
        ph = np.asarray(photo)
        ph = ph.astype(np.float64) / 255.0 if ph.dtype == np.uint8 else ph.astype(np.float64)
        Hr, Wr = ph.shape[:2]
        if ref.depth is None or np.asarray(ref.depth).shape != (Hr, Wr):
            raise ShapeError("reference depth", getattr(ref.depth, "shape", ()),
                             f"[{Hr}, {Wr}] (the photo's size)")
        r_ok = _valid(ref, alpha_min)
        u, v, z = _project(ref, X)
        inb = ok & (z > 1e-9) & (u >= 0.5) & (u <= Wr - 0.5) & (v >= 0.5) & (v <= Hr - 0.5)
        iy = np.clip(np.floor(np.where(inb, v, 0)).astype(np.int64), 0, Hr - 1)
        ix = np.clip(np.floor(np.where(inb, u, 0)).astype(np.int64), 0, Wr - 1)
        d_ref = np.asarray(ref.depth, np.float64)[iy, ix]
        sup = inb & r_ok[iy, ix] & (np.abs(z - d_ref) <= depth_tol * d_ref)
        if not sup.any():
            continue
        if ph.shape[-1] >= 4:
            # an object mask: a sample any of whose bilinear taps is masked out supports nothing
            warped = bilinear_sample(ph[..., :4], u[sup] - 0.5, v[sup] - 0.5)
            inm = warped[:, 3] >= 1.0 - 1e-6
            sup[sup] = inm
            warped = warped[inm, :3]
            if not sup.any():
                continue
        else:
            warped = bilinear_sample(ph[..., :3], u[sup] - 0.5, v[sup] - 0.5)
        sse[sup] += np.mean((warped - rgb[sup][:, :3]) ** 2, axis=-1)
        cnt[sup] += 1
    has = cnt > 0
    err = np.where(has, sse / np.maximum(cnt, 1), np.nan)
    if not has.any():
        return math.nan, 0.0, err
    mse = float(err[has].mean())
    return (math.inf if mse <= 0 else -10.0 * math.log10(mse)), float(has.mean()), err


# --------------------------------------------------------------------------- certainty
def certainty_support(view: RenderedView, grid_values: np.ndarray, bbox_min: np.ndarray,
                      bbox_max: np.ndarray, high: float, low: float, alpha_min: float = 0.5,
                      points: np.ndarray | None = None) -> tuple[float, float]:
    """``(certain_share, beyond_share)`` of a render against a certainty grid.

    Args:
        view: the render (depth, alpha in [0, 1]; alpha None = 1).
        grid_values: ``[R, R, R]`` certainty (usually dilated, :class:`TrustContext`).
        bbox_min, bbox_max: the grid's box.
        high: a point is *certain* when its voxel's C >= high.
        low: a point is *beyond* the certain region when outside the box or C < low.
        alpha_min: pixels with alpha below this (or no valid depth) are empty, i.e. beyond.
    Returns:
        ``certain_share = sum(alpha * certain) / (H W)``; ``beyond_share`` = share of pixels
        empty or beyond.
    """
    H, W = view.hw
    ok = _valid(view, alpha_min)
    alpha = np.ones((H, W)) if view.alpha is None else np.clip(np.asarray(view.alpha,
                                                                          np.float64), 0, 1)
    R = grid_values.shape[0]
    lo = np.asarray(bbox_min, np.float64)
    hi = np.asarray(bbox_max, np.float64)
    X = (lifted_points(view, alpha_min) if points is None else points)[ok]
    idx = np.floor((X - lo) * (R / (hi - lo))).astype(np.int64)
    idx = np.where((X == hi) & (idx == R), R - 1, idx)
    inside = np.all((idx >= 0) & (idx < R), axis=1)
    c = np.zeros(X.shape[0])
    i = idx[inside]
    c[inside] = grid_values[i[:, 0], i[:, 1], i[:, 2]]
    certain = np.zeros((H, W))
    certain[ok] = c >= high
    beyond = ~ok
    beyond[ok] = ~inside | (c < low)
    return float((alpha * certain).sum() / (H * W)), float(beyond.mean())


# --------------------------------------------------------------------------- geometry
def depth_edge_share(depth: np.ndarray, valid: np.ndarray, tau: float = 0.1) -> float:
    """Share of valid pixels with a 4-neighbour (valid too) whose depth differs by more than
    ``tau`` times the smaller of the two depths (0 when no pixel is valid)."""
    d = np.asarray(depth, np.float64)
    if not valid.any():
        return 0.0
    edge = np.zeros(d.shape, bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        both = valid[a] & valid[b]
        jump = both & (np.abs(d[a] - d[b]) > tau * np.minimum(d[a], d[b]))
        edge[a] |= jump
        edge[b] |= jump
    return float(edge[valid].mean())


def floater_share(depth: np.ndarray, valid: np.ndarray, window: int = 15, ratio: float = 0.6,
                  stride: int = 1) -> float:
    """Share of pixels that are isolated near-camera blobs: valid with a depth below
    ``ratio`` times the local median depth.

    The local median is taken on the depth subsampled every ``stride`` pixels (rows and
    columns; empty pixels count as far, 1000 x the farthest valid depth): pixel ``(i, j)``
    uses the median of the ``w x w`` subsampled block centred at ``(i // stride,
    j // stride)`` with ``w = 2 (window // (2 stride)) + 1`` (at least 3), edge values
    replicated, i.e. a neighbourhood about ``window`` pixels wide at ``stride^2`` less cost.
    ``stride = 1`` (the default, what the frozen model was fitted with) is the plain
    ``window x window`` median.

    No median is formed: ``d < ratio * median`` holds exactly when at least ``(n + 1) / 2``
    of the block's ``n = w^2`` values ``v`` satisfy ``d < ratio * v`` (the test is monotone in
    ``v``, and the median is the value of rank ``n // 2``), so a numba kernel counts them with
    an early exit. Same result, bit for bit, as scipy's ``median_filter`` (kept as
    :func:`floater_share_median`, the reference; tested).
    """
    d = np.asarray(depth, np.float64)
    valid = np.asarray(valid, bool)
    if not valid.any():
        return 0.0
    far = float(d[valid].max()) * 1e3
    d = np.ascontiguousarray(np.where(valid, d, far))
    s = max(1, int(stride))
    w = max(3, 2 * (int(window) // (2 * s)) + 1)
    small = np.ascontiguousarray(np.pad(d[::s, ::s], w // 2, mode="edge"))
    n = _floater_count(d, np.ascontiguousarray(valid), small, s, w, float(ratio))
    return float(n / d.size)


def floater_share_median(depth: np.ndarray, valid: np.ndarray, window: int = 15,
                         ratio: float = 0.6, stride: int = 1) -> float:
    """:func:`floater_share` through scipy's rank filter (the definition; the reference of
    the counting kernel, and the code before issue 63)."""
    from scipy.ndimage import median_filter

    d = np.asarray(depth, np.float64)
    if not valid.any():
        return 0.0
    far = float(d[valid].max()) * 1e3
    d = np.where(valid, d, far)
    s = max(1, int(stride))
    w = max(3, 2 * (int(window) // (2 * s)) + 1)
    med_small = median_filter(d[::s, ::s], size=w, mode="nearest")
    H, W = d.shape
    med = med_small[np.arange(H)[:, None] // s, np.arange(W)[None, :] // s]
    return float((valid & (d < ratio * med)).mean())


@njit(cache=True, nogil=True)
def _floater_count(d, valid, small, s, w, ratio):  # pragma: no cover - numba
    """Pixels of ``d [H, W]`` (valid) below ``ratio`` x the median of their ``w x w`` block
    of the subsampled depth (``small``: padded by ``w // 2`` with edge values), counted
    without sorting: see :func:`floater_share`."""
    H, W = d.shape
    n = w * w
    need = n - n // 2  # values v with d < ratio v needed for d < ratio * median
    total = 0
    for i in range(H):
        a = i // s
        for j in range(W):
            if not valid[i, j]:
                continue
            b = j // s
            x = d[i, j]
            hit = 0
            miss = 0
            done = False
            for y in range(a, a + w):
                for z in range(b, b + w):
                    if x < ratio * small[y, z]:
                        hit += 1
                        if hit >= need:
                            total += 1
                            done = True
                            break
                    else:
                        miss += 1
                        if miss > n - need:
                            done = True
                            break
                if done:
                    break
    return total


def view_angle_deg(view: RenderedView, train_poses: np.ndarray, fx, fy, cx, cy, width,
                   height, alpha_min: float = 0.5, stride: int = 2,
                   points: np.ndarray | None = None) -> float:
    """Median over valid pixels (every ``stride``-th) of the angle (deg) at the 3D point
    between the free view's ray and the nearest training ray through it; only training
    cameras with the point in front and inside the image count (180 when none). NaN when no
    pixel is valid.

    One numba pass over the points (every training camera per point, no ``[N, 3]``
    temporaries per camera); :func:`view_angle_deg_numpy` is the numpy definition it
    replaces (issue 63), equal to 1e-6 deg (tested; the same formulas, the projection
    summed in another order, which moves the cosine in its last bits)."""
    X, a = _angle_points(view, alpha_min, stride, points)
    if X is None:
        return math.nan
    P = np.ascontiguousarray(np.asarray(train_poses, np.float64).reshape(-1, 4, 4))
    intr = np.ascontiguousarray(np.stack([np.asarray(v, np.float64).reshape(-1)
                                          for v in (fx, fy, cx, cy, width, height)], 1))
    best = _best_cosine(np.ascontiguousarray(X), np.ascontiguousarray(a), P, intr)
    return float(np.median(np.degrees(np.arccos(np.clip(best, -1.0, 1.0)))))


def _angle_points(view, alpha_min, stride, points):
    """The valid every-``stride``-th lifted points ``[N, 3]`` and their unit rays from the
    view's centre, or ``(None, None)`` when no pixel is valid."""
    ok = _valid(view, alpha_min)[::stride, ::stride]
    if not ok.any():
        return None, None
    X = (lifted_points(view, alpha_min) if points is None else points)[::stride, ::stride][ok]
    a = X - np.asarray(view.world_from_cam, np.float64)[:3, 3]
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-300)
    return X, a


def view_angle_deg_numpy(view: RenderedView, train_poses: np.ndarray, fx, fy, cx, cy, width,
                         height, alpha_min: float = 0.5, stride: int = 2,
                         points: np.ndarray | None = None) -> float:
    """:func:`view_angle_deg` in numpy, camera by camera (the code before issue 63; the
    reference of the kernel)."""
    X, a = _angle_points(view, alpha_min, stride, points)
    if X is None:
        return math.nan
    best = np.full(X.shape[0], -1.0)  # best cosine
    for t in range(len(train_poses)):
        Pt = np.asarray(train_poses[t], np.float64)
        Xc = (X - Pt[:3, 3]) @ Pt[:3, :3]
        z = Xc[:, 2]
        zs = np.where(z > 1e-9, z, 1.0)
        u = fx[t] * Xc[:, 0] / zs + cx[t]
        v = fy[t] * Xc[:, 1] / zs + cy[t]
        inside = (z > 1e-9) & (u >= 0) & (u < width[t]) & (v >= 0) & (v < height[t])
        b = X - Pt[:3, 3]
        b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-300)
        best = np.where(inside, np.maximum(best, (a * b).sum(1)), best)
    return float(np.median(np.degrees(np.arccos(np.clip(best, -1.0, 1.0)))))


@njit(cache=True, nogil=True)
def _best_cosine(X, a, P, intr):  # pragma: no cover - numba
    """Per point of ``X [N, 3]`` (unit ray ``a [N, 3]`` from the free view), the largest
    cosine with the ray of a training camera ``P [T, 4, 4]`` (intrinsics ``intr [T, 6]``:
    fx, fy, cx, cy, width, height) that has the point in front and inside its image; -1
    when none."""
    N = X.shape[0]
    T = P.shape[0]
    out = np.full(N, -1.0)
    for i in range(N):
        best = -1.0
        for t in range(T):
            d0 = X[i, 0] - P[t, 0, 3]
            d1 = X[i, 1] - P[t, 1, 3]
            d2 = X[i, 2] - P[t, 2, 3]
            z = d0 * P[t, 0, 2] + d1 * P[t, 1, 2] + d2 * P[t, 2, 2]
            if not z > 1e-9:
                continue
            x = d0 * P[t, 0, 0] + d1 * P[t, 1, 0] + d2 * P[t, 2, 0]
            y = d0 * P[t, 0, 1] + d1 * P[t, 1, 1] + d2 * P[t, 2, 1]
            u = intr[t, 0] * x / z + intr[t, 2]
            v = intr[t, 1] * y / z + intr[t, 3]
            if not (u >= 0.0 and u < intr[t, 4] and v >= 0.0 and v < intr[t, 5]):
                continue
            nb = max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-300)
            c = a[i, 0] * (d0 / nb) + a[i, 1] * (d1 / nb) + a[i, 2] * (d2 / nb)
            if c > best:
                best = c
        out[i] = best
    return out


# --------------------------------------------------------------------------- combination
def trust_features(t: TrustScores | dict, brisque: float, black_ratio: float,
                   depth_validity: float) -> np.ndarray:
    """``[len(FEATURES)]`` feature vector of the model (NaN where a score is missing):
    ``photo_psnr`` clipped to 5..45 dB (5 dB when no pixel is supported), the view angle as
    ``log(1 + deg)``, and three derived terms: ``photo_blend``, the PSNR of an image whose
    supported share has the photometric error and the rest a 12 dB error,
    ``-10 log10(s 10^(-p/10) + (1 - s) 10^(-1.2))``; ``support_x_psnr = s p``; the squared
    black ratio."""
    d = t.as_dict() if isinstance(t, TrustScores) else dict(t)
    pp = d.get("photo_psnr", math.nan)
    sup = d.get("photo_support", math.nan)
    if sup == 0.0:
        pp = _PHOTO_PSNR_CLIP[0]
    elif np.isfinite(pp) or pp == math.inf:
        pp = float(np.clip(pp, *_PHOTO_PSNR_CLIP))
    ang = d.get("view_angle_deg", math.nan)
    with np.errstate(all="ignore"):
        blend = -10.0 * math.log10(sup * 10 ** (-pp / 10) + (1 - sup) * 10 ** (
            -_UNSUPPORTED_PSNR / 10)) if np.isfinite(pp) and np.isfinite(sup) else math.nan
    return np.array([pp, sup, d.get("certain_share", math.nan),
                     d.get("beyond_share", math.nan), d.get("depth_edges", math.nan),
                     d.get("floaters", math.nan), math.log1p(ang) if np.isfinite(ang)
                     else math.nan, brisque, black_ratio, depth_validity, blend, sup * pp,
                     black_ratio ** 2], np.float64)


def predict_psnr(features: np.ndarray, mean=None, scale=None, coef=None,
                 intercept: float | None = None) -> np.ndarray:
    """Predicted PSNR (dB) of renders from their features ``[..., len(FEATURES)]``:
    ``intercept + sum(coef * (x - mean) / scale)`` with NaN features imputed by the mean
    (the frozen constants unless given)."""
    mean = _MEAN if mean is None else np.asarray(mean, np.float64)
    scale = _SCALE if scale is None else np.asarray(scale, np.float64)
    coef = _COEF if coef is None else np.asarray(coef, np.float64)
    b = _INTERCEPT if intercept is None else float(intercept)
    z = (np.asarray(features, np.float64) - mean) / scale
    z = np.where(np.isfinite(z), z, 0.0)
    return b + z @ coef


def loss_weight(pred_psnr, ref_psnr: float = 25.0, floor: float = 0.0) -> np.ndarray:
    """Loss weight of free views by predicted PSNR: the ratio of a reference view's MSE to the
    view's predicted MSE, ``10 ** ((pred - ref) / 10)``, clipped to ``[floor, 1]`` (a view
    predicted 3 dB below ``ref_psnr`` weighs 0.5; NaN weighs ``floor``)."""
    p = np.asarray(pred_psnr, np.float64)
    w = np.power(10.0, (p - float(ref_psnr)) / 10.0)
    return np.clip(np.where(np.isfinite(w), w, floor), floor, 1.0)


# --------------------------------------------------------------------------- one view
class TrustContext:
    """What scoring a render needs besides the render: training cameras (at the render
    scale), their photos and renders (fetched lazily, cached), and the certainty grid.

    Args:
        train_poses, fx, fy, cx, cy, width, height: training cameras at the render scale.
        reference: ``i -> (photo [H_i, W_i, 3], RenderedView with depth)``, cached here.
        grid: ``CertaintyGrid`` or None (certainty scores are then NaN).
        cfg: ``schemas.freeview.TrustConfig`` (defaults when None).
    """

    def __init__(self, train_poses, fx, fy, cx, cy, width, height, reference, grid=None,
                 cfg=None, timer=None) -> None:
        from schemas.freeview import TrustConfig

        self.timer = timer  # ``timer(part)`` -> context manager (freeviews.run), or None
        self.cfg = cfg or TrustConfig()
        self.poses = np.asarray(train_poses, np.float64)
        self.intr = tuple(np.asarray(a, np.float64) for a in (fx, fy, cx, cy, width, height))
        self._reference = reference
        self._refs: dict[int, tuple] = {}
        self.grid = grid
        if grid is not None:
            from scipy.ndimage import maximum_filter

            self.dilated = maximum_filter(grid.values, size=3, mode="constant", cval=0.0)
            self.high = grid.quantile_threshold(self.cfg.certain_quantile)
            self.low = grid.quantile_threshold(self.cfg.beyond_quantile)

    def ref(self, i: int):
        if i not in self._refs:
            self._refs[i] = self._reference(int(i))
        return self._refs[i]

    def __call__(self, view: RenderedView, brisque: float, black_ratio: float,
                 depth_validity: float) -> TrustScores:
        return score_trust(view, self, brisque, black_ratio, depth_validity)


def score_trust(view: RenderedView, ctx: TrustContext, brisque: float, black_ratio: float,
                depth_validity: float) -> TrustScores:
    """Every trust score of one render and its predicted PSNR (:func:`predict_psnr`).

    The view is lifted to 3D once (:func:`lifted_points`) for all geometric scores; the
    training references it needs are fetched (rendered once per training view, cached by
    ``ctx``) before the photometric score. ``ctx.timer`` (if set) receives the seconds per
    part: ``trust_photometric``, ``trust_certainty``, ``trust_edges``, ``trust_floaters``,
    ``trust_angle``, ``trust_other``.
    """
    from contextlib import nullcontext

    tm = ctx.timer or (lambda part: nullcontext())
    c = ctx.cfg
    am = c.alpha_min
    with tm("trust_other"):
        ok = _valid(view, am)
        X = _lift(view, np.where(ok, view.depth, 1.0))
    with tm("trust_photometric"):
        near = nearest_training_views(view, ctx.poses, *ctx.intr, k=c.n_refs, alpha_min=am,
                                      max_angle_deg=c.ref_max_angle_deg, points=X)
    refs = [ctx.ref(int(i)) for i in near]
    with tm("trust_photometric"):
        pp, sup, _ = photometric_consistency(view, refs, am, c.depth_tol, points=X)
    cs = bs = math.nan
    if ctx.grid is not None:
        with tm("trust_certainty"):
            cs, bs = certainty_support(view, ctx.dilated, ctx.grid.bbox_min,
                                       ctx.grid.bbox_max, ctx.high, ctx.low, am, points=X)
    with tm("trust_edges"):
        edges = depth_edge_share(view.depth, ok, c.edge_tau)
    with tm("trust_floaters"):
        floaters = floater_share(view.depth, ok, c.floater_window, c.floater_ratio,
                                 c.floater_stride)
    with tm("trust_angle"):
        angle = view_angle_deg(view, ctx.poses, *ctx.intr, alpha_min=am, points=X)
    with tm("trust_other"):
        ts = TrustScores(photo_psnr=pp, photo_support=sup, certain_share=cs, beyond_share=bs,
                         depth_edges=edges, floaters=floaters, view_angle_deg=angle)
        pred = float(predict_psnr(trust_features(ts, brisque, black_ratio, depth_validity)))
    return TrustScores(**{**ts.as_dict(), "pred_psnr": pred})
