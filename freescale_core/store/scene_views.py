"""The views of one scene as a view sampler sees them: which are free, the capture order and
the view graph. One definition for the store's shard dataset (``store/dataset.py``) and the
LVSM sampler (``downstream/lvsm/sampler.py``, which re-exports it), kept in the store layer so
that the store imports nothing from ``downstream/``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SceneViews:
    """The views of one scene as the sampler sees them (dataset-agnostic).

    Attributes:
        scene_id: name used in error messages.
        is_free: ``[N]`` bool, True for free (generated) views.
        frame_index: ``[N]`` int64, position in the capture order for captured views (unique,
            >= 0; gaps allowed), -1 for free views.
        edges: view graph ``(src [E], dst [E], wiou [E])``, undirected, view ids ``0..N-1``,
            WIoU in [0, 1]. Self-loops are dropped; non-finite WIoU (FreeScale's pose-distance
            ablation stores NaN) becomes 0.5, i.e. no preference; values are clipped to [0, 1].
        view_weight: optional ``[N]`` loss-weight factor of free-view targets (captured views
            ignore it), e.g. ``freeviews.trust.loss_weight(views.parquet pred_psnr)``; None = 1.
    """

    scene_id: str
    is_free: np.ndarray
    frame_index: np.ndarray
    edges: tuple[np.ndarray, np.ndarray, np.ndarray]
    view_weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.is_free = np.asarray(self.is_free, dtype=bool).reshape(-1)  # [N]
        self.frame_index = np.asarray(self.frame_index, dtype=np.int64).reshape(-1)  # [N]
        n = self.is_free.shape[0]
        name = f"scene {self.scene_id!r}"
        if self.frame_index.shape[0] != n:
            raise ValueError(f"{name}: is_free has {n} views, frame_index "
                             f"{self.frame_index.shape[0]}")
        if np.any(self.frame_index[self.is_free] != -1):
            raise ValueError(f"{name}: free views must have frame_index -1")
        cap = self.frame_index[~self.is_free]
        if np.any(cap < 0) or np.unique(cap).size != cap.size:
            raise ValueError(f"{name}: captured frame_index values must be unique and >= 0")
        src, dst, w = (np.asarray(a).reshape(-1) for a in self.edges)
        if not src.shape == dst.shape == w.shape:
            raise ValueError(f"{name}: edge arrays differ in length "
                             f"({src.shape[0]}, {dst.shape[0]}, {w.shape[0]})")
        src, dst = src.astype(np.int64), dst.astype(np.int64)
        if src.size and (min(src.min(), dst.min()) < 0 or max(src.max(), dst.max()) >= n):
            raise ValueError(f"{name}: edge endpoints must lie in 0..{n - 1}")
        if self.view_weight is not None:
            vw = np.asarray(self.view_weight, dtype=np.float64).reshape(-1)
            if vw.shape[0] != n:
                raise ValueError(f"{name}: view_weight has {vw.shape[0]} values, not {n}")
            self.view_weight = np.clip(np.where(np.isfinite(vw), vw, 0.0), 0.0, None)
        keep = src != dst
        w = np.where(np.isfinite(w), w, 0.5).astype(np.float64)
        self.edges = (src[keep], dst[keep], np.clip(w[keep], 0.0, 1.0))

    @property
    def n_views(self) -> int:
        """N, captured + free."""
        return int(self.is_free.shape[0])

    @property
    def captured_order(self) -> np.ndarray:
        """``[N_captured]`` int64 ids of the captured views sorted by frame_index."""
        ids = np.flatnonzero(~self.is_free)
        return ids[np.argsort(self.frame_index[ids], kind="stable")]
