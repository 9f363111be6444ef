"""Typed read access to one published scene version: :class:`FreeViewSet`.

A published version (``STORE/scenes/<id>/vNNNN/``, see ``docs/STORE.md``) is self-contained:
training images at the published pinhole intrinsics (``images/``), sparse points
(``points.parquet``), every camera and its scores (``views.parquet``), the view graph, the
free-view RGB and depth (``arrays.zarr``) and the resolved config (``config.json``). This
module is the one place that knows that layout for reading; the shard packer, the exports and
the PyTorch loader all go through it.

"Dataset views" are the training views (``disposition == "train"``) and the stored free
views (``disposition == "free_view"``), in view-id order (training views first, in capture
order). Candidates that were not kept are in :attr:`FreeViewSet.views` but have no image.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from freescale_core.errors import StoreError
from freescale_core.geometry.cameras import Cameras
from freescale_core.store.layout import world_from_cam_column
from freescale_core.store.store import Store

DATASET_DISPOSITIONS = ("train", "free_view")


@dataclass
class ViewTable:
    """Per-view columns of the dataset views (training + free views), aligned.

    Attributes:
        view_id: ``[N]`` int64 ids in ``views.parquet``.
        kind: ``[N]`` ``train`` or ``candidate``.
        mode: ``[N]`` ``train`` or the trajectory mode.
        disposition: ``[N]`` ``train`` or ``free_view``.
        is_free: ``[N]`` bool.
        capture_index: ``[N]`` int64 capture order of training views, -1 for free views.
        name: ``[N]`` source image names (training views), ``""`` for free views.
        score_f, brisque, black_ratio, depth_validity: ``[N]`` float64 (NaN where unset).
        free_index: ``[N]`` int64 row in ``arrays.zarr/freeviews/*`` (-1 for training views).
        cameras: the ``N`` cameras (OpenCV ``world_from_cam``, pinhole pixels).
    """

    view_id: np.ndarray
    kind: np.ndarray
    mode: np.ndarray
    disposition: np.ndarray
    is_free: np.ndarray
    capture_index: np.ndarray
    name: np.ndarray
    score_f: np.ndarray
    brisque: np.ndarray
    black_ratio: np.ndarray
    depth_validity: np.ndarray
    free_index: np.ndarray
    cameras: Cameras

    def __len__(self) -> int:
        return len(self.view_id)


class FreeViewSet:
    """One published scene version, read lazily.

    Open with :meth:`open` (store root + scene id, resolves ``CURRENT``) or
    :meth:`from_version_dir`. Nothing heavy is read until asked for; the object holds no open
    file handles between calls except the zarr group, so it can be pickled to worker processes
    (the group is re-opened there).
    """

    def __init__(self, version_dir: str | Path, scene_id: str | None = None):
        self.version_dir = Path(version_dir)
        self.scene_id = scene_id or self.version_dir.parent.name
        if not (self.version_dir / "views.parquet").is_file():
            raise StoreError(f"scene {self.scene_id!r}: {self.version_dir} is not a published "
                             "version (no views.parquet)")
        self._views = None
        self._dataset = None
        self._zarr = None

    # ---- opening
    @classmethod
    def open(cls, store_root: str | Path, scene_id: str) -> "FreeViewSet":
        """The current published version of ``scene_id`` in the store at ``store_root``."""
        d = Store(store_root).current_version_dir(scene_id)
        if d is None:
            raise StoreError(f"scene {scene_id!r} has no published version in {store_root}")
        return cls(d, scene_id)

    @classmethod
    def from_version_dir(cls, version_dir: str | Path) -> "FreeViewSet":
        return cls(version_dir)

    @property
    def version(self) -> str:
        return self.version_dir.name

    def __getstate__(self):
        return {"version_dir": self.version_dir, "scene_id": self.scene_id}

    def __setstate__(self, st):
        self.__init__(st["version_dir"], st["scene_id"])

    def __repr__(self) -> str:
        return f"FreeViewSet({self.scene_id!r}, {self.version_dir})"

    # ---- tables
    @property
    def views(self):
        """The full ``views.parquet`` table (every camera, pyarrow)."""
        if self._views is None:
            self._views = pq.read_table(self.version_dir / "views.parquet")
        return self._views

    def _col(self, t, name, default, dtype):
        if name in t.column_names:
            return np.asarray(t.column(name).to_numpy(zero_copy_only=False)).astype(dtype)
        return np.full(t.num_rows, default, dtype)

    def dataset_views(self) -> ViewTable:
        """The training + free views as a :class:`ViewTable` (cached)."""
        if self._dataset is not None:
            return self._dataset
        import pyarrow.compute as pc

        t = self.views
        disp = t.column("disposition")
        t = t.filter(pc.is_in(disp, value_set=__import__("pyarrow").array(DATASET_DISPOSITIONS)))
        disposition = self._col(t, "disposition", "", object)
        is_free = disposition == "free_view"
        cap = self._col(t, "capture_index", -1, np.int64)
        if "capture_index" not in t.column_names:  # versions published before capture_index
            cap = np.where(is_free, -1, np.cumsum(~is_free) - 1)
        cams = Cameras(world_from_cam_column(t), *(self._col(t, k, np.nan, np.float64)
                                                    for k in ("fx", "fy", "cx", "cy")),
                       self._col(t, "width", 0, np.int64), self._col(t, "height", 0, np.int64))
        self._dataset = ViewTable(
            view_id=self._col(t, "view_id", -1, np.int64),
            kind=self._col(t, "kind", "", object), mode=self._col(t, "mode", "", object),
            disposition=disposition, is_free=is_free, capture_index=cap,
            name=self._col(t, "name", "", object),
            score_f=self._col(t, "score_f", np.nan, np.float64),
            brisque=self._col(t, "brisque", np.nan, np.float64),
            black_ratio=self._col(t, "black_ratio", np.nan, np.float64),
            depth_validity=self._col(t, "depth_validity", np.nan, np.float64),
            free_index=self._col(t, "free_index", -1, np.int64), cameras=cams)
        return self._dataset

    def cameras(self, which: str = "all") -> tuple[np.ndarray, Cameras]:
        """``(view_ids [N], Cameras)`` of ``which`` in ``all`` (train + free), ``train``,
        ``free``."""
        v = self.dataset_views()
        mask = {"all": np.ones(len(v), bool), "train": ~v.is_free, "free": v.is_free}.get(which)
        if mask is None:
            raise ValueError(f"which must be 'all', 'train' or 'free', got {which!r}")
        return v.view_id[mask], v.cameras.subset(np.flatnonzero(mask)) if mask.any() else \
            v.cameras.subset(np.zeros(0, np.int64))

    def graph(self, dataset_only: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """View-graph edges ``(src [E], dst [E], wiou [E] float32)`` in view ids; with
        ``dataset_only`` only edges between training / free views."""
        t = pq.read_table(self.version_dir / "view_graph.parquet")
        src = t.column("src").to_numpy().astype(np.int64)
        dst = t.column("dst").to_numpy().astype(np.int64)
        w = t.column("wiou").to_numpy().astype(np.float32)
        if dataset_only:
            keep = np.isin(src, self.dataset_views().view_id) & \
                np.isin(dst, self.dataset_views().view_id)
            src, dst, w = src[keep], dst[keep], w[keep]
        return src, dst, w

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """Sparse points ``(xyz [P, 3] float64 world, rgb [P, 3] uint8)``."""
        p = self.version_dir / "points.parquet"
        if not p.is_file():
            raise StoreError(f"scene {self.scene_id!r}: {p} is missing (version published "
                             "before points were stored; re-run publish)")
        t = pq.read_table(p)
        xyz = np.stack([t.column(c).to_numpy() for c in "xyz"], 1).astype(np.float64)
        rgb = np.stack([t.column(c).to_numpy() for c in "rgb"], 1).astype(np.uint8)
        return xyz, rgb

    def config(self) -> dict:
        """The resolved pipeline config of this version (``config.json``): ``{"config_hash",
        "config"}``; ``{}`` for versions published before it was stored."""
        p = self.version_dir / "config.json"
        return json.loads(p.read_text()) if p.is_file() else {}

    @property
    def gaussians_ply(self) -> Path | None:
        p = self.version_dir / "gaussians.ply"
        return p if p.is_file() else None

    # ---- pixels
    def _arrays(self):
        if self._zarr is None:
            import zarr

            self._zarr = zarr.open_group(str(self.version_dir / "arrays.zarr"), mode="r")
        return self._zarr

    def _row(self, view_id: int) -> int:
        v = self.dataset_views()
        k = np.flatnonzero(v.view_id == int(view_id))
        if not len(k):
            raise KeyError(f"scene {self.scene_id!r}: view {view_id} is neither a training "
                           "view nor a stored free view")
        return int(k[0])

    def image_path(self, view_id: int) -> Path:
        """Published training image file of a training view."""
        v = self.dataset_views()
        r = self._row(view_id)
        if v.is_free[r]:
            raise KeyError(f"scene {self.scene_id!r}: view {view_id} is a free view (no file)")
        return self.version_dir / "images" / str(v.name[r])

    def rgb(self, view_id: int) -> np.ndarray:
        """``[h, w, 3]`` uint8 image of a dataset view at its own size (``width``, ``height``
        of its camera): the published training image, or the free view cropped from the
        zero-padded zarr array."""
        from freescale_core.scene.scene import read_rgb

        v = self.dataset_views()
        r = self._row(view_id)
        h, w = int(v.cameras.height[r]), int(v.cameras.width[r])
        if not v.is_free[r]:
            img = read_rgb(self.image_path(view_id), self.scene_id)
        else:
            img = np.asarray(self._arrays()["freeviews/rgb"][int(v.free_index[r])])
            img = img[:h, :w]
        if img.shape[:2] != (h, w):
            raise StoreError(f"scene {self.scene_id!r}: view {view_id} image is "
                             f"{img.shape[1]}x{img.shape[0]}, its camera says {w}x{h}")
        return img

    def confidence(self, view_id: int) -> np.ndarray | None:
        """``[h, w]`` float32 in [0, 1]: the fixer's per-pixel confidence of a free view it
        made (``freeviews/confidence``); None for training views and for free views of a
        rectifier that gives none."""
        v = self.dataset_views()
        r = self._row(view_id)
        arrays = self._arrays()
        if not v.is_free[r] or "freeviews/confidence" not in arrays:
            return None
        h, w = int(v.cameras.height[r]), int(v.cameras.width[r])
        c = np.asarray(arrays["freeviews/confidence"][int(v.free_index[r])])[:h, :w]
        return c.astype(np.float32) / 255.0

    def depth(self, view_id: int) -> np.ndarray:
        """``[h, w]`` float32 camera-z depth of a free view (0 where empty)."""
        v = self.dataset_views()
        r = self._row(view_id)
        if not v.is_free[r]:
            raise KeyError(f"scene {self.scene_id!r}: view {view_id} is a training view "
                           "(no rendered depth)")
        h, w = int(v.cameras.height[r]), int(v.cameras.width[r])
        return np.asarray(self._arrays()["freeviews/depth"][int(v.free_index[r])])[:h, :w]


def open_scenes(store_root: str | Path, scene_ids: list[str] | None = None) -> list[FreeViewSet]:
    """Every published (status ``ok``) scene of a store, or those in ``scene_ids``."""
    st = Store(store_root)
    if not st.root.is_dir():
        raise StoreError(f"no store at {store_root}")
    ids = scene_ids or [s for s in st.scene_ids() if st.read_status(s).get("status") == "ok"]
    missing = [s for s in ids if s not in st.scene_ids()]
    if missing:
        raise StoreError(f"scenes {missing} are not in the store {store_root}")
    return [FreeViewSet.open(store_root, s) for s in ids]
