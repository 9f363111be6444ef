"""The 3D Gaussian scene representation shared by every stage.

Parameters are stored *unactivated*, as 3DGS/gsplat PLY files store them. Activations are
applied exactly once, by the properties below (the authors' code applied them twice).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from freescale_core.errors import DegenerateSceneError, ShapeError

SH_C0 = 0.28209479177387814  # Y_0^0


@dataclass
class Gaussians:
    """N anisotropic 3D Gaussians.

    Attributes:
        means: ``[N, 3]`` float32 centres mu (world units).
        log_scales: ``[N, 3]`` float32 log standard deviations s (scale = exp(s)).
        quats_wxyz: ``[N, 4]`` float32 rotations (not necessarily normalised).
        opacity_logits: ``[N]`` float32 (alpha = sigmoid(logit)).
        sh: ``[N, K, 3]`` float32 spherical-harmonic colour coefficients, K = (deg + 1)^2;
            ``sh[:, 0]`` is the DC term (colour = SH_C0 * sh_dc + 0.5 at degree 0).
    """

    means: np.ndarray
    log_scales: np.ndarray
    quats_wxyz: np.ndarray
    opacity_logits: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float32)
        n = self.means.shape[0]
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32)
        self.quats_wxyz = np.ascontiguousarray(self.quats_wxyz, dtype=np.float32)
        self.opacity_logits = np.ascontiguousarray(self.opacity_logits, dtype=np.float32).reshape(n)
        self.sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        if self.sh.ndim == 2:
            self.sh = self.sh.reshape(n, -1, 3)
        checks = [("means", self.means, (n, 3)), ("log_scales", self.log_scales, (n, 3)),
                  ("quats_wxyz", self.quats_wxyz, (n, 4))]
        for name, a, shape in checks:
            if a.shape != shape:
                raise ShapeError(name, a.shape, str(list(shape)))
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ShapeError("sh", self.sh.shape, "[N, K, 3]")
        k = self.sh.shape[1]
        if int(round(np.sqrt(k))) ** 2 != k:
            raise ShapeError("sh", self.sh.shape, "[N, (deg+1)^2, 3]")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def alphas(self) -> np.ndarray:
        """``[N]`` activated opacity sigmoid(logit), applied once."""
        return 1.0 / (1.0 + np.exp(-self.opacity_logits.astype(np.float64)))

    @property
    def scales(self) -> np.ndarray:
        """``[N, 3]`` activated scales exp(s), applied once."""
        return np.exp(self.log_scales.astype(np.float64))

    @property
    def volumes(self) -> np.ndarray:
        """``[N]`` Vol_j = prod_k exp(s_jk) (Eq. 1), computed in log space."""
        return np.exp(self.log_scales.astype(np.float64).sum(axis=1))

    @property
    def colors_dc(self) -> np.ndarray:
        """``[N, 3]`` view-independent RGB in [0, 1] from the DC term."""
        return np.clip(SH_C0 * self.sh[:, 0].astype(np.float64) + 0.5, 0.0, 1.0)

    def subset(self, idx) -> "Gaussians":
        return Gaussians(self.means[idx], self.log_scales[idx], self.quats_wxyz[idx],
                         self.opacity_logits[idx], self.sh[idx])

    def validate(self, scene: str = "?", path: str | None = None) -> None:
        """Raise :class:`DegenerateSceneError` on NaN/inf parameters or an empty set."""
        if len(self) == 0:
            raise DegenerateSceneError(scene, "no Gaussians", path)
        for name in ("means", "log_scales", "quats_wxyz", "opacity_logits", "sh"):
            a = getattr(self, name)
            bad = ~np.isfinite(a)
            if bad.any():
                rows = np.unique(np.nonzero(bad.reshape(len(self), -1))[0])
                raise DegenerateSceneError(
                    scene, f"{len(rows)} Gaussians have non-finite {name} "
                    f"(first rows {rows[:5].tolist()})", path)
        if np.any(np.linalg.norm(self.quats_wxyz, axis=1) < 1e-12):
            raise DegenerateSceneError(scene, "zero-length quaternion in Gaussians", path)

    @staticmethod
    def from_points(points: np.ndarray, colors: np.ndarray, sh_degree: int = 0,
                    opacity: float = 0.5, scale: np.ndarray | float | None = None) -> "Gaussians":
        """Isotropic Gaussians at ``points [N, 3]`` with ``colors [N, 3]`` in [0, 1].

        The default scale is the mean distance to the 3 nearest neighbours (3DGS init).
        """
        pts = np.asarray(points, dtype=np.float64)
        n = pts.shape[0]
        if scale is None:
            from scipy.spatial import cKDTree

            k = min(4, n)
            d, _ = cKDTree(pts).query(pts, k=k)
            d = d[:, 1:] if k > 1 else np.ones((n, 1))
            scale = np.sqrt(np.maximum(np.mean(d ** 2, axis=1), 1e-10))
        scale = np.broadcast_to(np.asarray(scale, dtype=np.float64), (n,))
        sh = np.zeros((n, (sh_degree + 1) ** 2, 3), np.float32)
        sh[:, 0] = (np.asarray(colors, dtype=np.float64) - 0.5) / SH_C0
        logit = np.log(opacity / (1.0 - opacity))
        return Gaussians(pts, np.repeat(np.log(scale)[:, None], 3, axis=1),
                         np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), np.full(n, logit), sh)
