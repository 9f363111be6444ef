"""The typed ``Scene`` every reader returns and every later stage consumes."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from freescale_core.geometry.cameras import Cameras
from freescale_core.scene.images import natural_order, read_rgb


def reindex_tracks(tracks: tuple[np.ndarray, np.ndarray], idx, n: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Tracks over ``n`` views re-indexed to the views ``idx`` (old index of each new one):
    view ``idx[j]`` becomes ``j``, any other (and -1) becomes -1."""
    new_pos = np.full(n + 1, -1, np.int64)  # slot -1 stays -1
    new_pos[np.asarray(idx, np.int64)] = np.arange(len(idx))
    return tracks[0], new_pos[tracks[1]]


@dataclass
class Scene:
    """One captured scene: pinhole images with exact cameras and sparse points.

    Attributes:
        scene_id: stable id (the scene folder's name unless given).
        root: the scene's input folder.
        image_paths: ``N`` paths of *pinhole* images (undistorted copies when the source
            camera model had distortion), aligned with ``cameras``.
        image_names: ``N`` image names as the source model names them.
        cameras: ``N`` cameras, internal convention (OpenCV axes, world_from_cam).
        points_xyz: ``[P, 3]`` float64 sparse points (world).
        points_rgb: ``[P, 3]`` uint8 colours of the sparse points.
        source_format: ``colmap``, ``nerfstudio``, ``images`` (SfM run here) or ``sample``.
        camera_models: the source camera model name of each camera (``N`` strings).
        undistorted: whether images were undistorted to pinhole by the reader.
        capture_order: ``[N]`` indices of the cameras in capture order (image-name order
            for unordered sources); the paper's OOD split takes the first 70% of this.
        extras: reader-specific facts (e.g. ``n_registered`` for SfM, ``applied_transform``).
        mask_paths: ``N`` object masks aligned with ``image_paths`` (same size, undistorted and
            resized like them), or None when the capture has none. A mask is a single-channel
            image, nonzero = object (keep); :meth:`load_mask` reads it as ``[H, W]`` bool.
        points_tracks: ``(ptr [P + 1], views [T])``: sparse point ``k`` was triangulated from
            the views ``views[ptr[k]:ptr[k + 1]]`` (camera indices; -1 for an image that is
            not a view of this scene), or None when the source gives no tracks (nerfstudio,
            an SfM without them). :meth:`points_seen_by` reads them.
    """

    scene_id: str
    root: Path
    image_paths: list[Path]
    image_names: list[str]
    cameras: Cameras
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    source_format: str
    camera_models: list[str]
    undistorted: bool = False
    capture_order: np.ndarray | None = None
    extras: dict = field(default_factory=dict)
    mask_paths: list[Path] | None = None
    points_tracks: tuple[np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        self.image_paths = [Path(p) for p in self.image_paths]
        if self.mask_paths is not None:
            self.mask_paths = [Path(p) for p in self.mask_paths]
            if len(self.mask_paths) != len(self.image_paths):
                raise ValueError(f"scene {self.scene_id!r}: {len(self.mask_paths)} masks for "
                                 f"{len(self.image_paths)} images")
        self.points_xyz = np.asarray(self.points_xyz, dtype=np.float64).reshape(-1, 3)
        self.points_rgb = np.asarray(self.points_rgb, dtype=np.uint8).reshape(-1, 3)
        if self.capture_order is None:  # natural name order: img2 before img10
            self.capture_order = natural_order(list(self.image_names))
        self.capture_order = np.asarray(self.capture_order, dtype=np.int64)
        if self.points_tracks is not None:
            ptr, views = (np.asarray(a, np.int64).reshape(-1) for a in self.points_tracks)
            if len(ptr) != len(self.points_xyz) + 1 or ptr[-1] != len(views):
                raise ValueError(f"scene {self.scene_id!r}: tracks of {len(ptr) - 1} points "
                                 f"({len(views)} observations) for {len(self.points_xyz)} points")
            self.points_tracks = (ptr, views)

    def __len__(self) -> int:
        return len(self.image_paths)

    @property
    def n_images(self) -> int:
        return len(self.image_paths)

    def load_image(self, i: int) -> np.ndarray:
        """Image ``i`` as ``[H, W, 3]`` uint8 RGB; raises a scene-naming error if unreadable."""
        return read_rgb(self.image_paths[i], self.scene_id)

    @property
    def has_masks(self) -> bool:
        """True when every image has an object mask (:attr:`mask_paths`)."""
        return getattr(self, "mask_paths", None) is not None  # pickles from before masks

    def load_mask(self, i: int) -> np.ndarray | None:
        """Mask of image ``i`` as ``[H, W]`` bool (True = object), or None without masks."""
        if not self.has_masks:
            return None
        from freescale_core.scene.images import read_mask

        return read_mask(self.mask_paths[i], self.scene_id)

    def bounds(self, percentile: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Robust box ``(min [3], max [3])`` of sparse points and camera centres."""
        pts = np.concatenate([self.points_xyz, self.cameras.centers]) if len(self.points_xyz) \
            else self.cameras.centers
        return (np.percentile(pts, percentile, axis=0), np.percentile(pts, 100 - percentile, axis=0))

    def points_seen_by(self, idx, min_views: int = 2) -> np.ndarray | None:
        """``[P]`` bool: the sparse points views ``idx`` alone could have triangulated, i.e.
        at least ``min_views`` of a point's track are in ``idx`` (all of the track when it is
        shorter; a point with an empty track is kept). None when the scene has no tracks.

        A held-out evaluation starts from these only: the others were placed, and coloured,
        with a held-out view (docs/RECON.md, "Sparse points a held-out view made")."""
        tracks = getattr(self, "points_tracks", None)  # pickles from before tracks
        if tracks is None:
            return None
        ptr, views = tracks
        inside = np.zeros(len(self) + 1, bool)  # slot -1: an image not in this scene
        inside[np.asarray(idx, np.int64)] = True
        c = np.concatenate([[0], np.cumsum(inside[views], dtype=np.int64)])
        hits = c[ptr[1:]] - c[ptr[:-1]]
        lens = np.diff(ptr)
        return (lens == 0) | (hits >= np.minimum(min_views, lens))

    def subset(self, idx) -> "Scene":
        """The scene restricted to cameras ``idx`` (in index order), capture order kept.

        Sparse points are kept whole, their tracks re-indexed (a dropped view becomes -1):
        :meth:`points_seen_by` then tells which of them the kept views alone could have made."""
        idx = np.sort(np.asarray(idx, dtype=np.int64))
        rank = np.empty(len(self), np.int64)
        rank[self.capture_order] = np.arange(len(self))
        tracks = getattr(self, "points_tracks", None)
        if tracks is not None:
            tracks = reindex_tracks(tracks, idx, len(self))
        return Scene(
            scene_id=self.scene_id, root=self.root,
            image_paths=[self.image_paths[i] for i in idx],
            image_names=[self.image_names[i] for i in idx],
            cameras=self.cameras.subset(idx), points_xyz=self.points_xyz,
            points_rgb=self.points_rgb, source_format=self.source_format,
            camera_models=[self.camera_models[i] for i in idx], undistorted=self.undistorted,
            capture_order=np.argsort(rank[idx], kind="stable"), extras=dict(self.extras),
            mask_paths=[self.mask_paths[i] for i in idx] if self.has_masks else None,
            points_tracks=tracks)

    def views_for(self, split: str) -> tuple["Scene", "Scene | None"]:
        """``(generation scene, held-out scene or None)`` for a ``recon_split``.

        With ``ood`` / ``every8`` the held-out views are kept out of every generation stage
        (reconstruction, selection, free views), so an evaluation on them is honest."""
        train_idx, test_idx = self.split(split)
        if len(test_idx) == 0:
            return self, None
        return self.subset(train_idx), self.subset(test_idx)

    def split(self, kind: str = "ood", train_fraction: float = 0.7,
              every: int = 8) -> tuple[np.ndarray, np.ndarray]:
        """``(train_idx, test_idx)`` camera indices.

        ``ood``: first ``train_fraction`` of frames in capture order train, the rest test
        (the paper's out-of-distribution protocol). ``every8``: every ``every``-th frame
        (in capture order) is a test frame (the usual 3DGS protocol). ``all``: no test.
        A scene whose folder lists its held-out views (``heldout.txt``, kept in
        ``extras["heldout_names"]``) uses that list for ``ood`` and ``every8``.
        """
        order = self.capture_order
        n = len(order)
        if kind == "all":
            return order.copy(), np.zeros(0, np.int64)
        listed = self.extras.get("heldout_names") if kind in ("ood", "every8") else None
        if listed:
            held = set(listed)
            test = np.array([self.image_names[i] in held for i in order], bool)
            return order[~test].copy(), order[test].copy()
        if kind == "ood":
            k = min(n - 1, max(1, int(round(train_fraction * n))))
            return order[:k].copy(), order[k:].copy()
        if kind == "every8":
            mask = (np.arange(n) % every) == 0
            return order[~mask].copy(), order[mask].copy()
        raise ValueError(f"unknown split kind {kind!r}; expected 'ood', 'every8' or 'all'")
