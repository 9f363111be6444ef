"""Feasibility of candidate cameras (METHOD.md stage 4).

A candidate is rejected when its centre is outside the scene box (``outside_box``) or inside
known structure (``inside_structure``): the voxel containing the centre (and optionally its
Chebyshev neighbourhood) is occupied, i.e. its certainty is at least a quantile of the
non-empty voxels. Voxel lookup uses the grid's own ``[ix, iy, iz]`` indexing (the authors
swapped x and z when sampling).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.select import FeasibilityConfig

from freescale_core.select.certainty import CertaintyGrid

__all__ = ["Feasibility", "check_feasibility", "occupancy_grid"]


@dataclass
class Feasibility:
    """Result of stage 4.

    Attributes:
        feasible: ``[N]`` bool.
        reason: ``[N]`` str: "" (feasible), "outside_box" or "inside_structure".
        occupancy_threshold: the certainty at or above which a voxel is structure.
    """

    feasible: np.ndarray
    reason: np.ndarray
    occupancy_threshold: float

    @property
    def counts(self) -> dict[str, int]:
        return {"n_feasible": int(self.feasible.sum()),
                "n_infeasible_outside_box": int(np.sum(self.reason == "outside_box")),
                "n_infeasible_inside_structure": int(np.sum(self.reason == "inside_structure"))}


def occupancy_grid(grid: CertaintyGrid, quantile: float) -> tuple[np.ndarray, float]:
    """``([R, R, R] bool occupied, threshold)``: C >= the quantile of non-empty voxels."""
    thr = grid.quantile_threshold(quantile)
    return (grid.values >= thr) & (grid.values > 0), thr


def check_feasibility(centers_world: np.ndarray, grid: CertaintyGrid,
                      cfg: FeasibilityConfig | None = None,
                      train_centers: np.ndarray | None = None,
                      margin: float = 0.1) -> Feasibility:
    """Stage 4 feasibility of camera centres.

    Args:
        centers_world: ``[N, 3]`` camera centres (world).
        grid: certainty grid.
        cfg: which tests, occupancy quantile, neighbourhood radius.
        train_centers: ``[T, 3]`` training camera centres; with ``cfg.include_cameras`` their
            box (widened by ``margin`` of its extent per side) also counts as inside.
    Returns:
        :class:`Feasibility`; ``outside_box`` takes precedence over ``inside_structure``.
    """
    cfg = cfg or FeasibilityConfig()
    c = np.asarray(centers_world, dtype=np.float64).reshape(-1, 3)
    n = c.shape[0]
    reason = np.full(n, "", dtype="<U16")
    inside = grid.inside_box(c) if cfg.check_box else np.ones(n, bool)
    if cfg.check_box and cfg.include_cameras and train_centers is not None and len(train_centers):
        tc = np.asarray(train_centers, dtype=np.float64).reshape(-1, 3)
        lo, hi = tc.min(axis=0), tc.max(axis=0)
        pad = margin * np.maximum(hi - lo, 1e-9 * (1.0 + np.abs(tc).max()))
        inside |= np.all((c >= lo - pad) & (c <= hi + pad), axis=1)
    reason[~inside] = "outside_box"
    occ, thr = occupancy_grid(grid, cfg.occupancy_quantile)
    if cfg.check_structure and np.isfinite(thr):
        idx = grid.voxel_index(c)
        R = grid.R
        r = cfg.neighbourhood
        hit = np.zeros(n, bool)
        offs = np.arange(-r, r + 1)
        for dx in offs:
            for dy in offs:
                for dz in offs:
                    j = idx + np.array([dx, dy, dz])
                    ok = np.all((j >= 0) & (j < R), axis=1)
                    jj = j[ok]
                    h = np.zeros(n, bool)
                    h[ok] = occ[jj[:, 0], jj[:, 1], jj[:, 2]]
                    hit |= h
        reason[inside & hit] = "inside_structure"
    return Feasibility(reason == "", reason, float(thr))
