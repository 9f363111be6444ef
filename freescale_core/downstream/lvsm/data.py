"""In-memory scenes for LVSM training and evaluation (dataset-agnostic).

A :class:`SceneTensors` holds one scene's views as fixed-size tensors (captured frames and,
optionally, free views) plus its :class:`SceneViews` (what the sampler sees). The trainer
only ever touches this record, so any source plugs in through one adapter:

* :func:`load_sample_scene` reads a scene folder written by ``write_sample_scene`` (images,
  poses from ``scene.json``), optionally adding free views (:func:`add_views`);
* :func:`from_shard_record` maps a per-scene record of the shard Dataset (``images``
  ``[V, 3, H, W]`` in [0, 1], ``fxfycxcy`` ``[V, 4]``, ``world_from_cam`` ``[V, 4, 4]`` OpenCV,
  ``is_free`` ``[V]``, optional ``frame_index`` and view-graph ``edges``).

:func:`collate` turns a list of ``(SceneTensors, Sample)`` into the model's batch.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from freescale_core.downstream.lvsm.sampler import Sample, SceneViews

__all__ = [
    "SceneTensors",
    "add_views",
    "collate",
    "from_shard_record",
    "load_sample_scene",
    "resize_views",
]


@dataclass
class SceneTensors:
    """One scene's views as tensors.

    Attributes:
        views: the sampler's view of the scene (is_free, frame_index, view graph).
        images: ``[N, 3, H, W]`` float32 RGB in [0, 1].
        K: ``[N, 4]`` float64 ``fx, fy, cx, cy`` in pixels of ``images``.
        world_from_cam: ``[N, 4, 4]`` float64 camera-to-world, OpenCV axes.
        confidence: ``[N, H, W]`` float32 in [0, 1], per-pixel trust in each view (the
            fixer's confidence for the free views it made, 1 for photos); None = all 1.
    """

    views: SceneViews
    images: torch.Tensor
    K: torch.Tensor
    world_from_cam: torch.Tensor
    confidence: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.views.n_views
        name = f"scene {self.views.scene_id!r}"
        if self.images.ndim != 4 or self.images.shape[:2] != (n, 3):
            raise ValueError(f"{name}: images must be [{n}, 3, H, W], got "
                             f"{tuple(self.images.shape)}")
        if tuple(self.K.shape) != (n, 4):
            raise ValueError(f"{name}: K must be [{n}, 4], got {tuple(self.K.shape)}")
        if tuple(self.world_from_cam.shape) != (n, 4, 4):
            raise ValueError(f"{name}: world_from_cam must be [{n}, 4, 4], got "
                             f"{tuple(self.world_from_cam.shape)}")
        if self.confidence is not None and tuple(self.confidence.shape) != (
                n, *self.images.shape[2:]):
            raise ValueError(f"{name}: confidence must be [{n}, H, W] like images, got "
                             f"{tuple(self.confidence.shape)}")

    @property
    def scene_id(self) -> str:
        return self.views.scene_id

    @property
    def hw(self) -> tuple[int, int]:
        return int(self.images.shape[2]), int(self.images.shape[3])


def resize_views(rgb: np.ndarray, K: np.ndarray, width: int, height: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Resize uint8 ``[N, h, w, 3]`` views to ``width x height`` (area filter) and scale their
    intrinsics ``[N, 4]`` (pixel-centre convention: ``c' = c * s``).

    Returns:
        ``(images [N, 3, height, width] float32 in [0, 1], K [N, 4] float64)``.
    """
    import cv2

    rgb = np.asarray(rgb)
    h, w = rgb.shape[1:3]
    out = np.empty((len(rgb), height, width, 3), np.uint8)
    for i, im in enumerate(rgb):
        out[i] = im if (h, w) == (height, width) else cv2.resize(
            im, (width, height), interpolation=cv2.INTER_AREA)
    sx, sy = width / w, height / h
    K = np.asarray(K, np.float64) * np.array([sx, sy, sx, sy])
    return out.transpose(0, 3, 1, 2).astype(np.float32) / 255.0, K


def _chain_edges(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Consecutive captured frames linked (a stand-in graph when no view graph is given)."""
    i = np.arange(n - 1)
    return i, i + 1, np.full(n - 1, 0.5)


def load_sample_scene(scene_dir: str | Path, width: int, height: int) -> SceneTensors:
    """A sample-scene folder's captured frames at ``width x height`` (no free views)."""
    from freescale_core.scene.sample import SampleWorld
    from freescale_core.scene.scene import read_rgb

    scene_dir = Path(scene_dir)
    world = SampleWorld.load(scene_dir)
    cams = world.cameras
    if cams is None:
        raise ValueError(f"scene {scene_dir.name!r}: scene.json has no capture cameras")
    rgb = np.stack([read_rgb(scene_dir / "images" / n, scene_dir.name)
                    for n in world.image_names])
    K = np.stack([cams.fx, cams.fy, cams.cx, cams.cy], -1)
    imgs, K = resize_views(rgb, K, width, height)
    n = len(imgs)
    views = SceneViews(scene_dir.name, np.zeros(n, bool), np.arange(n), _chain_edges(n))
    return SceneTensors(views, torch.from_numpy(imgs), torch.from_numpy(K),
                        torch.from_numpy(np.asarray(cams.world_from_cam, np.float64)))


def add_views(scene: SceneTensors, rgb: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray,
              edges: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
              confidence: np.ndarray | None = None) -> SceneTensors:
    """The scene plus free views (uint8 ``rgb [M, h, w, 3]``, ``K [M, 4]`` in pixels of
    ``rgb``, ``world_from_cam [M, 4, 4]``), resized to the scene's size.

    Args:
        edges: view graph over the combined ids (captured first, free views after); None keeps
            the scene's edges (free views then only reachable by the random branch).
        confidence: ``[M, h, w]`` per-pixel confidence of the new views (float in [0, 1] or
            uint8 0-255, area-resized like the images); the scene's other views get 1.
            None: the scene keeps its confidence (new views 1 if it has one).
    """
    H, W = scene.hw
    if len(rgb) == 0:
        return scene
    imgs, Kf = resize_views(rgb, K, W, H)
    m = len(imgs)
    conf = scene.confidence
    if confidence is not None or conf is not None:
        old = conf if conf is not None else torch.ones(scene.views.n_views, H, W)
        new = torch.ones(m, H, W)
        if confidence is not None:
            import cv2

            c = np.asarray(confidence)
            c = c.astype(np.float32) / 255.0 if c.dtype == np.uint8 else c.astype(np.float32)
            if len(c) != m:
                raise ValueError(f"scene {scene.scene_id!r}: {len(c)} confidence maps for "
                                 f"{m} views")
            new = torch.from_numpy(np.stack([
                x if x.shape == (H, W) else cv2.resize(x, (W, H), interpolation=cv2.INTER_AREA)
                for x in c]).clip(0.0, 1.0))
        conf = torch.cat([old, new])
    v = scene.views
    views = SceneViews(v.scene_id, np.concatenate([v.is_free, np.ones(m, bool)]),
                       np.concatenate([v.frame_index, -np.ones(m, np.int64)]),
                       v.edges if edges is None else edges)
    return SceneTensors(views, torch.cat([scene.images, torch.from_numpy(imgs)]),
                        torch.cat([scene.K, torch.from_numpy(Kf)]),
                        torch.cat([scene.world_from_cam,
                                   torch.as_tensor(np.asarray(world_from_cam, np.float64))]),
                        conf)


def from_shard_record(rec: dict[str, Any], scene_id: str | None = None) -> SceneTensors:
    """Adapter from a shard Dataset's per-scene record to :class:`SceneTensors`.

    Expected keys: ``images [V, 3, H, W]`` float in [0, 1], ``fxfycxcy [V, 4]``,
    ``world_from_cam [V, 4, 4]`` (OpenCV), ``is_free [V]``; optional ``frame_index [V]``
    (default: captured views in record order), ``edges`` = ``(src, dst, wiou)`` (default: a
    chain over the captured frames), ``scene_id``, ``confidence [V, H, W]`` float in [0, 1]
    (the shards' per-pixel confidence; absent: None).
    """
    is_free = np.asarray(rec["is_free"], bool)
    if "frame_index" in rec:
        fi = np.asarray(rec["frame_index"], np.int64)
    else:
        fi = np.full(len(is_free), -1, np.int64)
        fi[~is_free] = np.arange(int((~is_free).sum()))
    n_cap = int((~is_free).sum())
    if "edges" in rec and rec["edges"] is not None:
        edges = rec["edges"]
    else:
        cap = np.flatnonzero(~is_free)[np.argsort(fi[~is_free])]
        s, d, w = _chain_edges(n_cap)
        edges = (cap[s], cap[d], w)
    sid = scene_id or str(rec.get("scene_id", "?"))
    return SceneTensors(SceneViews(sid, is_free, fi, edges),
                        torch.as_tensor(rec["images"], dtype=torch.float32),
                        torch.as_tensor(rec["fxfycxcy"], dtype=torch.float64),
                        torch.as_tensor(rec["world_from_cam"], dtype=torch.float64),
                        None if rec.get("confidence") is None
                        else torch.as_tensor(rec["confidence"], dtype=torch.float32))


def collate(items: list[tuple[SceneTensors, Sample]]) -> dict[str, torch.Tensor]:
    """Batch of examples -> the model's inputs and targets.

    Returns:
        ``images [B, Vi, 3, H, W]``, ``in_c2w [B, Vi, 4, 4]``, ``in_K [B, Vi, 4]``,
        ``tgt_c2w [B, Vt, 4, 4]``, ``tgt_K [B, Vt, 4]``, ``target [B, Vt, 3, H, W]``,
        ``weight [B, Vt]``, and ``confidence [B, Vt, H, W]`` (1 for views without one) when
        any item's scene has a confidence.
    """
    def gather(attr: str, key: str) -> torch.Tensor:
        return torch.stack([getattr(sc, attr)[torch.as_tensor(getattr(s, key))]
                            for sc, s in items])

    out = dict(
        images=gather("images", "input_ids"), in_c2w=gather("world_from_cam", "input_ids"),
        in_K=gather("K", "input_ids"), tgt_c2w=gather("world_from_cam", "target_ids"),
        tgt_K=gather("K", "target_ids"), target=gather("images", "target_ids"),
        weight=torch.stack([torch.as_tensor(s.target_weight) for _, s in items]))
    if any(sc.confidence is not None for sc, _ in items):
        out["confidence"] = torch.stack([
            sc.confidence[torch.as_tensor(s.target_ids)] if sc.confidence is not None
            else torch.ones(len(s.target_ids), *sc.hw) for sc, s in items])
    return out
