"""Quality filter of rendered free views (METHOD.md stage 7).

Three no-reference scores per rendered view, all computed offline on the CPU:

* **BRISQUE/100** (Mittal et al. 2012) with the SVM model bundled in the ``brisque`` package
  (its features and model; the package itself is only called, never edited).
  OpenCV contrib's ``cv2.quality.QualityBRISQUE`` computes the same statistic but needs the
  ``brisque_model_live.yml`` / ``brisque_range_live.yml`` files, which the opencv wheels do not
  ship; we use the ``brisque`` package instead. Two adaptations, made here and not in
  site-packages: (1) its feature vector holds 1-element arrays, which numpy >= 2 refuses to turn
  into floats, so it is flattened before scaling and the SVM predict; (2) its Gaussian local
  mean/variance (``scipy.signal.convolve2d``, zero padding) is replaced by ``cv2.filter2D`` with
  a zero border, the same numbers to ~1e-15 and ~3x faster; (3) the SVR is evaluated in numpy
  (libsvm's predict varies in its last bits from call to call, which breaks determinism). A
  constant image (no structure, the fit is undefined and the package returns NaN) scores 1.0,
  the worst.
* **black ratio**: fraction of pixels that are exactly black (authors) *or* empty (alpha below
  ``empty_alpha``; ours, because our renderer composites over a background colour).
* **depth-range validity** on the central crop: min-max normalised depth, 95th minus 5th
  percentile; 0 when fewer than 10% of the crop's pixels have a valid depth (authors).
"""

from __future__ import annotations

import threading
from dataclasses import asdict, dataclass
from functools import lru_cache

import cv2
import numpy as np
from numba import njit

from schemas.freeview import QualityConfig

from freescale_core.errors import ShapeError

__all__ = [
    "QualityScores",
    "brisque_score",
    "black_ratio",
    "depth_validity",
    "score_view",
    "passes",
    "failure_reasons",
    "to_uint8",
]


# --------------------------------------------------------------------------- BRISQUE
_MODEL_LOCK = threading.Lock()


def _brisque_model():
    """The shared BRISQUE model, built once. Scenes run in concurrent threads, and libsvm's
    ``svm_load_model`` is not thread-safe: two first calls at once crashed the process
    (segfault), so the first load is serialised. Scoring itself is numpy and cv2."""
    with _MODEL_LOCK:
        return _load_brisque_model()


@lru_cache(maxsize=1)
def _load_brisque_model():
    """The ``brisque`` package's model, with the two adaptations described in the module doc."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from brisque import BRISQUE

    class _Brisque(BRISQUE):
        def calculate_mscn_coefficients(self, image, kernel_size=6, sigma=7 / 6):
            # same maths as the package (its local_deviation included), cv2 instead of scipy:
            # a symmetric kernel, so correlation == convolution; zero border == 'same' mode.
            kernel = self.gaussian_kernel2d(kernel_size, sigma=sigma)
            img = np.ascontiguousarray(image, dtype=np.float64)
            mu = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_CONSTANT)
            mu2 = cv2.filter2D(img * img, -1, kernel, borderType=cv2.BORDER_CONSTANT)
            sigma_map = np.sqrt(np.abs(mu * mu - mu2))
            return (img - mu) / (sigma_map + 1.0 / 255.0)

        def scale_features(self, features):
            flat = np.concatenate([np.ravel(np.asarray(f, dtype=np.float64)) for f in features])
            return super().scale_features(flat)

        def calculate_brisque_features(self, image, kernel_size=7, sigma=7 / 6):
            # the package's features with its five AGGD fits fed by one numba pass over the
            # MSCN map (its sums over masked copies of each map were ~60% of the time):
            # same formulas, sums in another order (equal to ~1e-12, tested)
            mscn = np.ascontiguousarray(self.calculate_mscn_coefficients(image, kernel_size,
                                                                         sigma))
            out = []
            for k, sums in enumerate(_aggd_sums(mscn)):
                alpha, mean, sl, sr = _aggd_fit(*sums)
                out += [alpha, (sl ** 2 + sr ** 2) / 2] if k == 0 else [alpha, mean, sl ** 2,
                                                                       sr ** 2]
            return np.array(out, dtype=np.float64)

    model = _Brisque(url=False)
    # The SVR (RBF kernel) evaluated in numpy with a fixed summation order: libsvm's own
    # predict is parallel and its last bits vary from call to call.
    svm = model.model
    if svm.get_svm_type() != 3 or svm.param.kernel_type != 2:  # EPSILON_SVR, RBF
        raise RuntimeError("the bundled BRISQUE model is no longer an RBF epsilon-SVR")
    n_feat = 36
    sv = np.zeros((svm.get_nr_sv(), n_feat))
    for i, d in enumerate(svm.get_SV()):
        for k, v in d.items():
            if 1 <= k <= n_feat:
                sv[i, k - 1] = v
    model._sv = sv
    model._sv_coef = np.array([c[0] for c in svm.get_sv_coef()], dtype=np.float64)
    model._rho = float(svm.rho[0])
    model._gamma = float(svm.param.gamma)
    return model


@njit(cache=True, nogil=True)
def _aggd_sums(m):  # pragma: no cover - numba
    """``[5, 6]`` sums for the AGGD fits of the MSCN map ``m`` and its four pair products
    (horizontal, vertical, main and secondary diagonal, the package's order): per map
    ``(n, sum |x|, sum x^2, n(x < 0), sum x^2 over x < 0, n(x >= 0))``; the sum of squares
    over ``x >= 0`` is ``sum x^2`` minus the negative part, computed separately below."""
    H, W = m.shape
    out = np.zeros((5, 7))
    for i in range(H):
        for j in range(W):
            a = m[i, j]
            for k in range(5):
                if k == 0:
                    x = a
                elif k == 1:
                    if j + 1 >= W:
                        continue
                    x = a * m[i, j + 1]
                elif k == 2:
                    if i + 1 >= H:
                        continue
                    x = a * m[i + 1, j]
                elif k == 3:
                    if i + 1 >= H or j + 1 >= W:
                        continue
                    x = a * m[i + 1, j + 1]
                else:
                    if i + 1 >= H or j + 1 >= W:
                        continue
                    x = m[i + 1, j] * m[i, j + 1]
                x2 = x * x
                out[k, 0] += 1.0
                out[k, 1] += abs(x)
                out[k, 2] += x2
                if x < 0:
                    out[k, 3] += 1.0
                    out[k, 4] += x2
                else:
                    out[k, 5] += 1.0
                    out[k, 6] += x2
    return out


def _aggd_fit(n, s_abs, s_sq, n_neg, s_neg, n_pos, s_pos):
    """The ``brisque`` package's ``asymmetric_generalized_gaussian_fit`` from the sums of
    :func:`_aggd_sums` (same formulas, same root finder and start): ``(alpha, mean,
    sigma_l, sigma_r)``."""
    from scipy import optimize, special

    with np.errstate(all="ignore"):
        f = np.float64
        r_hat = (f(s_abs) / n) ** 2 / (f(s_sq) / n)
        left, right = f(s_neg) / f(n_neg), f(s_pos) / f(n_pos)
        gamma = np.sqrt(left) / np.sqrt(right)
        R_hat = r_hat * ((gamma ** 3 + 1) * (gamma + 1)) / ((gamma ** 2 + 1) ** 2)

        def phi(z):
            return special.gamma(2 / z) ** 2 / (special.gamma(1 / z) * special.gamma(3 / z))

        alpha = optimize.root(lambda z: phi(z) - R_hat, [0.2]).x[0]
        sl, sr = np.sqrt(left), np.sqrt(right)
        const = np.sqrt(special.gamma(1 / alpha) / special.gamma(3 / alpha))
        mean = (sr - sl) * const * (special.gamma(2 / alpha) / special.gamma(1 / alpha))
    return alpha, mean, sl, sr


def _svr_predict(model, scaled: np.ndarray) -> float:
    """libsvm's epsilon-SVR prediction, sum_i coef_i exp(-gamma |sv_i - x|^2) - rho."""
    d2 = np.sum((model._sv - scaled[None, :]) ** 2, axis=1)
    return float(np.dot(model._sv_coef, np.exp(-model._gamma * d2)) - model._rho)


def _gray(rgb_u8: np.ndarray) -> np.ndarray:
    """uint8 RGB ``[H, W, 3]`` -> float64 luminance in [0, 1] (skimage rgb2gray weights)."""
    import skimage.color

    return skimage.color.rgb2gray(rgb_u8)


def brisque_features(rgb: np.ndarray) -> np.ndarray:
    """The 36 BRISQUE features (18 at full, 18 at half resolution) of an RGB image.

    Args:
        rgb: ``[H, W, 3]`` uint8, or float in [0, 1] (quantised to uint8 first).
    Returns:
        ``[36]`` float64.
    """
    model = _brisque_model()
    gray = _gray(to_uint8(rgb))
    full = model.calculate_brisque_features(gray, kernel_size=7, sigma=7 / 6)
    half = cv2.resize(gray, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_CUBIC)
    low = model.calculate_brisque_features(half, kernel_size=7, sigma=7 / 6)
    return np.concatenate([np.ravel(np.asarray(f, dtype=np.float64)) for f in (*full, *low)])


def brisque_score(rgb: np.ndarray) -> float:
    """BRISQUE/100 of an image: lower is better; the paper rejects >= 0.5 (stage 7).

    Args:
        rgb: ``[H, W, 3]`` uint8, or float in [0, 1] (quantised to uint8 first, i.e. the
            image that would be stored is the one scored).
    Returns:
        BRISQUE / 100 (typically 0..1, may leave that range slightly); 1.0 for an image with
        no structure (constant), where the statistic is undefined.
    """
    if rgb.ndim != 3 or rgb.shape[2] not in (3, 4) or min(rgb.shape[:2]) < 8:
        raise ShapeError("rgb", rgb.shape, "[H>=8, W>=8, 3]")
    rgb = rgb[..., :3]
    u8 = to_uint8(rgb)
    if int(u8.max()) == int(u8.min()):
        return 1.0
    model = _brisque_model()
    with np.errstate(all="ignore"):
        feats = brisque_features(u8)
        if not np.all(np.isfinite(feats)):
            return 1.0
        score = _svr_predict(model, model.scale_features(feats))
    return score / 100.0 if np.isfinite(score) else 1.0


# --------------------------------------------------------------------------- other scores
def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """``[H, W, C]`` uint8 unchanged; float in [0, 1] -> rounded, clipped uint8."""
    if rgb.dtype == np.uint8:
        return rgb
    return np.clip(np.rint(np.asarray(rgb, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def black_ratio(rgb: np.ndarray, alpha: np.ndarray | None = None, empty_alpha: float = 0.05
                ) -> float:
    """Fraction of black or empty pixels (stage 7; authors reject > 20%).

    Args:
        rgb: ``[H, W, 3]`` uint8 or float in [0, 1]; a pixel is black when every channel is
            0 after quantisation to uint8 (the authors' "exactly black").
        alpha: optional ``[H, W]`` accumulated opacity; pixels with alpha < ``empty_alpha``
            count as empty too (whatever background colour they were composited over).
        empty_alpha: see above.
    Returns:
        Fraction in [0, 1].
    """
    u8 = to_uint8(rgb)
    if u8.ndim != 3:
        raise ShapeError("rgb", u8.shape, "[H, W, 3]")
    bad = np.all(u8[..., :3] == 0, axis=-1)
    if alpha is not None:
        if alpha.shape != bad.shape:
            raise ShapeError("alpha", alpha.shape, f"{list(bad.shape)}")
        bad |= ~(np.asarray(alpha) >= empty_alpha)  # NaN alpha counts as empty
    return float(bad.mean())


def _central_crop(a: np.ndarray, crop: float) -> np.ndarray:
    H, W = a.shape[:2]
    ch, cw = max(1, int(round(H * crop))), max(1, int(round(W * crop)))
    y0, x0 = (H - ch) // 2, (W - cw) // 2
    return a[y0:y0 + ch, x0:x0 + cw]


def depth_validity(depth: np.ndarray, alpha: np.ndarray | None = None, crop: float = 0.7,
                   depth_alpha: float = 0.5, min_valid_fraction: float = 0.1) -> float:
    """Depth-range validity on the central crop (stage 7; paper rejects <= 0.1).

    The valid depths of the central ``crop`` x ``crop`` window are min-max normalised to
    [0, 1]; the score is their 95th minus 5th percentile. A fronto-parallel wall (one depth)
    scores 0, a view with real depth structure scores up to ~0.9.

    Args:
        depth: ``[H, W]`` camera-z depth (world units).
        alpha: optional ``[H, W]`` accumulated opacity; depth is valid where alpha >=
            ``depth_alpha`` (and the depth is finite and > 0).
        crop: side fraction of the central window.
        depth_alpha: see above.
        min_valid_fraction: score 0 when fewer crop pixels than this fraction are valid.
    Returns:
        Score in [0, 1].
    """
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ShapeError("depth", depth.shape, "[H, W]")
    valid = np.isfinite(depth) & (depth > 0)
    if alpha is not None:
        if alpha.shape != depth.shape:
            raise ShapeError("alpha", alpha.shape, f"{list(depth.shape)}")
        valid &= np.asarray(alpha) >= depth_alpha
    d = _central_crop(depth, crop)
    v = _central_crop(valid, crop)
    if v.mean() < min_valid_fraction or not v.any():
        return 0.0
    vals = d[v].astype(np.float64)
    lo, hi = vals.min(), vals.max()
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):
        return 0.0
    norm = (vals - lo) / (hi - lo)
    p5, p95 = np.percentile(norm, [5.0, 95.0])
    return float(p95 - p5)


# --------------------------------------------------------------------------- the filter
@dataclass(frozen=True)
class QualityScores:
    """The three stage-7 scores of one rendered view."""

    brisque: float  # BRISQUE / 100, lower is better
    black_ratio: float  # fraction of black/empty pixels
    depth_validity: float  # 95th - 5th percentile of normalised central depth

    def as_dict(self) -> dict:
        return asdict(self)


def score_view(rgb: np.ndarray, depth: np.ndarray, alpha: np.ndarray | None,
               cfg: QualityConfig | None = None) -> QualityScores:
    """All three stage-7 scores of one render.

    Args:
        rgb: ``[H, W, 3]`` float in [0, 1] or uint8.
        depth: ``[H, W]`` camera-z depth.
        alpha: ``[H, W]`` accumulated opacity, or None.
        cfg: thresholds and crop (paper defaults when None).
    """
    cfg = cfg or QualityConfig()
    return QualityScores(
        brisque=brisque_score(rgb),
        black_ratio=black_ratio(rgb, alpha, cfg.empty_alpha),
        depth_validity=depth_validity(depth, alpha, cfg.crop, cfg.depth_alpha,
                                      cfg.min_valid_fraction),
    )


def failure_reasons(scores: QualityScores, cfg: QualityConfig | None = None) -> list[str]:
    """Names of the failed tests (empty when the view passes)."""
    cfg = cfg or QualityConfig()
    out = []
    if not scores.black_ratio <= cfg.black_ratio_max:
        out.append("black")
    if not scores.brisque < cfg.brisque_max:
        out.append("brisque")
    if not scores.depth_validity > cfg.depth_validity_min:
        out.append("depth")
    return out


def passes(scores: QualityScores, cfg: QualityConfig | None = None) -> bool:
    """Stage 7 rule: black ratio <= 0.2, BRISQUE/100 < 0.5, depth validity > 0.1."""
    return not failure_reasons(scores, cfg)
