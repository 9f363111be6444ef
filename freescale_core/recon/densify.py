"""MCMC densification of 3D Gaussians (METHOD.md stage 1: "MCMC densification").

Follows 3DGS-MCMC (Kheradmand et al., 2024), written from the paper's equations:

* **Relocation**: dead Gaussians (opacity <= ``min_opacity``) are moved onto live ones drawn
  with probability proportional to opacity. A source drawn ``c`` times is shared by
  ``N = c + 1`` Gaussians; all N get the opacity and scale that keep the rendered footprint
  (paper Eq. 9)::

      alpha_new = 1 - (1 - alpha_old)^(1/N)
      scale_new = scale_old * alpha_old / D(N, alpha_new)
      D(N, a)   = sum_{i=1..N} sum_{k=0..i-1} C(i-1, k) (-1)^k a^(k+1) / sqrt(k+1)
                = sum_{k=1..N} (-1)^(k-1) C(N, k) a^k / sqrt(k)      (hockey-stick identity)

* **Growth**: new Gaussians are added the same way (sources drawn by opacity), up to a target
  count per densification.
* **Position noise** (paper Eq. 10): ``mu += lambda_noise * lr * sigmoid(-k (alpha - t)) *
  Sigma @ eps``, eps ~ N(0, I), k = 100, t = 0.005: only near-transparent Gaussians wander.

Parameters are held as a dict of tensors ``{"means" [N,3], "log_scales" [N,3],
"quats_wxyz" [N,4], "opacity_logits" [N], "sh_dc" [N,1,3], "sh_rest" [N,K-1,3]}``; every
function here edits ``.data`` in place (no autograd) and says which rows it touched so the
optimiser can reset their moments.
"""

from __future__ import annotations

from functools import lru_cache
from math import comb

import numpy as np
import torch

NOISE_K = 100.0
NOISE_T = 0.005


@lru_cache(maxsize=8)
def _footprint_coeffs(max_copies: int) -> np.ndarray:
    """``[max_copies + 1, max_copies + 1]`` table: row N holds (-1)^(k-1) C(N, k) / sqrt(k)."""
    table = np.zeros((max_copies + 1, max_copies + 1))
    for n in range(1, max_copies + 1):
        for k in range(1, n + 1):
            table[n, k] = (-1) ** (k - 1) * comb(n, k) / np.sqrt(k)
    return table


def split_opacity_scale(opacity: np.ndarray, n_copies: np.ndarray, max_copies: int = 51
                        ) -> tuple[np.ndarray, np.ndarray]:
    """MCMC Eq. 9: opacity and scale factor when one Gaussian becomes ``N`` copies.

    Args:
        opacity: ``[M]`` activated opacities alpha_old in (0, 1).
        n_copies: ``[M]`` int N >= 1 (clamped to ``max_copies``).
    Returns:
        ``(alpha_new [M], scale_ratio [M])``: each copy gets opacity alpha_new and scale
        ``scale_old * scale_ratio``. N = 1 gives ``(alpha_old, 1)``.
    """
    a_old = np.clip(np.asarray(opacity, np.float64), 1e-7, 1 - 1e-7)
    n = np.clip(np.asarray(n_copies, np.int64), 1, max_copies)
    a_new = 1.0 - np.power(1.0 - a_old, 1.0 / n)
    coeff = _footprint_coeffs(max_copies)[n]  # [M, max_copies + 1]
    powers = a_new[:, None] ** np.arange(max_copies + 1)[None, :]
    denom = np.sum(coeff * powers, axis=1)
    return a_new, a_old / np.maximum(denom, 1e-12)


def _sample_by_opacity(opacity: np.ndarray, candidates: np.ndarray, n: int,
                       rng: np.random.Generator) -> np.ndarray:
    p = opacity[candidates].astype(np.float64)
    p = p / p.sum()
    return candidates[rng.choice(len(candidates), size=n, replace=True, p=p)]


def _apply_split(params: dict[str, torch.Tensor], sources: np.ndarray, min_opacity: float,
                 max_copies: int) -> np.ndarray:
    """Give every drawn source (with repeats) its shared opacity/scale; return unique sources."""
    uniq, counts = np.unique(sources, return_counts=True)
    op = torch.sigmoid(params["opacity_logits"].data[uniq]).double().numpy()
    a_new, ratio = split_opacity_scale(op, counts + 1, max_copies)
    a_new = np.clip(a_new, min_opacity, 1.0 - 1e-6)
    logit = np.log(a_new) - np.log1p(-a_new)
    idx = torch.from_numpy(uniq)
    dt = params["opacity_logits"].dtype
    params["opacity_logits"].data[idx] = torch.from_numpy(logit).to(dt)
    params["log_scales"].data[idx] += torch.from_numpy(np.log(ratio)).to(dt)[:, None]
    return uniq


def relocate_dead(params: dict[str, torch.Tensor], rng: np.random.Generator,
                  min_opacity: float = 0.005, max_copies: int = 51
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Move dead Gaussians onto live ones drawn by opacity (MCMC relocation).

    Returns:
        ``(dead [D], sources [S])`` row indices whose values changed (optimizer moments of
        both must be reset). Empty when nothing is dead or nothing is alive.
    """
    opacity = torch.sigmoid(params["opacity_logits"].data).double().numpy()
    return relocate_rows(params, np.nonzero(opacity <= min_opacity)[0], rng, min_opacity,
                         max_copies)


def relocate_rows(params: dict[str, torch.Tensor], rows: np.ndarray, rng: np.random.Generator,
                  min_opacity: float = 0.005, max_copies: int = 51
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Move the given rows onto live Gaussians outside ``rows`` drawn by opacity (MCMC
    relocation of Gaussians flagged for another reason than low opacity: escaped the scene,
    too large).

    Returns:
        ``(rows [D], sources [S])`` as :func:`relocate_dead`; empty when no candidate source.
    """
    rows = np.unique(np.asarray(rows, np.int64))
    if len(rows) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    opacity = torch.sigmoid(params["opacity_logits"].data).double().numpy()
    ok = opacity > min_opacity
    ok[rows] = False
    alive = np.nonzero(ok)[0]
    if len(alive) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    sources = _sample_by_opacity(opacity, alive, len(rows), rng)
    uniq = _apply_split(params, sources, min_opacity, max_copies)
    src, dst = torch.from_numpy(sources), torch.from_numpy(rows)
    for p in params.values():
        p.data[dst] = p.data[src]
    return rows, uniq


def grow(params: dict[str, torch.Tensor], n_new: int, rng: np.random.Generator,
         min_opacity: float = 0.005, max_copies: int = 51) -> tuple[dict[str, torch.Tensor],
                                                                    np.ndarray]:
    """Append ``n_new`` Gaussians copied from sources drawn by opacity (MCMC growth).

    Returns:
        ``(params, sources)``: new parameter tensors (length N + n_new; leaf tensors with
        ``requires_grad``) and the unique source rows whose values changed.
    """
    if n_new <= 0:
        return params, np.zeros(0, np.int64)
    opacity = torch.sigmoid(params["opacity_logits"].data).double().numpy()
    candidates = np.nonzero(opacity > min_opacity)[0]
    if len(candidates) == 0:
        candidates = np.arange(len(opacity))
    sources = _sample_by_opacity(np.maximum(opacity, 1e-12), candidates, n_new, rng)
    uniq = _apply_split(params, sources, min_opacity, max_copies)
    src = torch.from_numpy(sources)
    out = {k: torch.cat([p.data, p.data[src]]).requires_grad_(True) for k, p in params.items()}
    return out, uniq


def covariance(log_scales: torch.Tensor, quats_wxyz: torch.Tensor) -> torch.Tensor:
    """``[N, 3, 3]`` world covariances R diag(exp(2 s)) R^T."""
    q = quats_wxyz / torch.linalg.norm(quats_wxyz, dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    R = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        dim=-1).reshape(-1, 3, 3)
    M = R * torch.exp(log_scales)[:, None, :]
    return M @ M.transpose(1, 2)


def position_noise(params: dict[str, torch.Tensor], scale: float,
                   generator: torch.Generator) -> None:
    """MCMC Eq. 10: add ``scale * sigmoid(-k (alpha - t)) * Sigma @ eps`` to the means in place.

    Args:
        scale: lambda_noise * current means learning rate.
    """
    with torch.no_grad():
        means = params["means"].data
        alpha = torch.sigmoid(params["opacity_logits"].data)
        gate = torch.sigmoid(NOISE_K * ((1.0 - alpha) - (1.0 - NOISE_T)))
        eps = torch.randn(means.shape, generator=generator, dtype=means.dtype)
        cov = covariance(params["log_scales"].data, params["quats_wxyz"].data)
        means += scale * gate[:, None] * torch.einsum("nij,nj->ni", cov, eps)
