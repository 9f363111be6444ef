"""``freescale inspect``: what a scene folder holds, read from the model only (fast).

Never undistorts, never runs SfM, never decodes images (image sizes come from the camera
model, or from image headers for an image-only folder).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from freescale_core.geometry.cameras import invert_pose


def _robust_bounds(points: np.ndarray, centers: np.ndarray, percentile: float = 1.0):
    pts = np.concatenate([points.reshape(-1, 3), centers.reshape(-1, 3)])
    pts = pts[np.isfinite(pts).all(axis=1)]
    if len(pts) == 0:
        return None, None
    return (np.percentile(pts, percentile, axis=0).tolist(),
            np.percentile(pts, 100 - percentile, axis=0).tolist())


def inspect_scene(path: str | Path, scene_id: str | None = None, cfg=None) -> dict:
    """Summarise a scene folder without loading it.

    Args:
        path: scene folder (or COLMAP model folder, or transforms.json).
        scene_id: id for errors; default the folder's name.
        cfg: optional :class:`schemas.ingest.IngestConfig` (``format``, ``downscale``).
    Returns:
        JSON-able dict: ``scene_id``, ``format``, ``root``, ``model_path``, ``images_dir``,
        ``n_images`` (registered views; image files for an image-only folder),
        ``n_image_files``, ``camera_models`` (unique, sorted), ``needs_undistortion``,
        ``needs_sfm``, ``image_sizes`` (unique ``[w, h]``), ``n_points``, ``bounds_min``,
        ``bounds_max`` (1st/99th percentile of points + camera centres; None if unknown).
    Raises:
        The same :class:`SceneError` subclasses as :func:`freescale_core.scene.io.load_scene` for a
        model that cannot be read.
    """
    from schemas.ingest import IngestConfig

    from freescale_core.scene.io import detect_format
    from freescale_core.scene.io.common import header_size, list_images

    cfg = cfg or IngestConfig()
    src = detect_format(path, cfg.format, scene_id, cfg.downscale)
    sid = scene_id or src.root.name
    out: dict = {"scene_id": sid, "format": src.format, "root": str(src.root),
                 "model_path": None if src.model_path is None else str(src.model_path),
                 "images_dir": str(src.images_dir), "needs_sfm": src.format == "images"}

    if src.format == "images":
        names = list_images(src.images_dir, recursive=src.images_dir != src.root)
        sizes = sorted({header_size(sid, src.images_dir / n) for n in names})
        out.update(n_images=len(names), n_image_files=len(names), camera_models=[],
                   needs_undistortion=True, image_sizes=[list(s) for s in sizes], n_points=0,
                   bounds_min=None, bounds_max=None)
        return out

    if src.format == "colmap":
        from freescale_core.scene.io.colmap import raw_from_reconstruction, read_reconstruction

        rec = read_reconstruction(sid, src.model_path)
        raw = raw_from_reconstruction(sid, rec, src.model_path, src.images_dir)
        n_files = len(list_images(src.images_dir)) if src.images_dir.is_dir() else 0
    else:
        from freescale_core.scene.io.nerfstudio import read_transforms_raw

        raw = read_transforms_raw(sid, src.model_path, cfg.downscale)
        n_files = sum(1 for n in raw.names if (raw.images_dir / n).is_file())

    from freescale_core.scene.io.undistort import is_pinhole

    cfw = raw.cam_from_world
    finite = np.isfinite(cfw).all(axis=(1, 2))
    centers = invert_pose(cfw[finite])[:, :3, 3] if finite.any() else np.zeros((0, 3))
    bmin, bmax = _robust_bounds(raw.points_xyz, centers)
    out.update(
        n_images=len(raw.names), n_image_files=n_files,
        camera_models=sorted({c.model.name for c in raw.cameras}),
        needs_undistortion=any(not is_pinhole(c) for c in raw.cameras),
        image_sizes=sorted({(int(c.width), int(c.height)) for c in raw.cameras}),
        n_points=int(len(raw.points_xyz)), bounds_min=bmin, bounds_max=bmax,
    )
    out["image_sizes"] = [list(s) for s in out["image_sizes"]]
    if raw.extras.get("n_model_images", len(raw.names)) != len(raw.names):
        out["n_unregistered"] = raw.extras["n_model_images"] - len(raw.names)
    if not finite.all():
        out["n_nonfinite_poses"] = int((~finite).sum())
    return out
