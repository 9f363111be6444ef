"""From a camera model as read from disk (any format) to the checked, pinhole ``Scene``.

Every reader (COLMAP, transforms.json, SfM) produces a :class:`RawModel`; :func:`assemble`
applies the paper's input pre-filter (registered views, finite poses, usable camera models,
image set = model set, decodable images) and makes the images pinhole (undistorted or resized
copies in an atomic cache when needed).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from freescale_core.geometry.cameras import Cameras, invert_pose
from freescale_core.errors import CameraModelError, DegenerateSceneError
from freescale_core.scene.scene import Scene, reindex_tracks
from freescale_core.scene.io.common import (
    build_cached_folder,
    check_image_set,
    decode_sizes,
    file_stamp,
    fingerprint,
)
from freescale_core.scene.io.undistort import can_undistort, is_pinhole, pinhole_intrinsics, resize_into, undistort_into


@dataclass
class RawModel:
    """Cameras and points as a reader found them (no checks, no undistortion yet).

    Attributes:
        names: ``N`` image names, relative to ``images_dir`` (posix).
        cam_from_world: ``[N, 4, 4]`` float64 world-to-camera, OpenCV axes.
        cameras: ``N`` pycolmap cameras (the source lens model of each image).
        points_xyz: ``[P, 3]`` float64 sparse points (world), ``points_rgb`` ``[P, 3]`` uint8.
        images_dir: folder the names are relative to.
        pose_file: the file that holds the poses (named in pose errors).
        camera_file: the file that holds the intrinsics (named in camera errors).
        source_format: ``colmap``, ``nerfstudio`` or ``images``.
        capture_order: ``[N]`` indices in capture order, or None for natural name order.
        model_names: every image name the model lists (registered or not), for the count check;
            None skips the check (SfM on a folder: unregistered images are expected).
        count_folders: folders (relative to ``images_dir``) whose image files must be exactly
            the model's; None means ``images_dir`` itself, recursively.
        stamp_files: files whose content identifies the model (cache keys).
        extras: reader facts copied into ``Scene.extras``.
        mask_paths: ``N`` object masks aligned with ``names`` (absolute), or None.
        mask_source: where the masks were found (named in messages), e.g. ``masks/``.
        points_tracks: ``(ptr [P + 1], views [T])``: point ``k`` was observed in images
            ``views[ptr[k]:ptr[k + 1]]`` (indices into ``names``, -1 for an image the model
            does not register), or None when the source gives no tracks.
    """

    names: list[str]
    cam_from_world: np.ndarray
    cameras: list
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    images_dir: Path
    pose_file: Path
    camera_file: Path
    source_format: str
    capture_order: np.ndarray | None = None
    model_names: list[str] | None = None
    count_folders: list[str] | None = None
    stamp_files: list[Path] = field(default_factory=list)
    extras: dict = field(default_factory=dict)
    mask_paths: list[Path] | None = None
    mask_source: str = ""
    points_tracks: tuple[np.ndarray, np.ndarray] | None = None


ROTATION_TOL = 1e-4
"""A pose rotation with max |R^T R - I| up to this is orthonormalised (SVD); beyond, rejected."""


def check_poses(scene_id: str, raw: RawModel) -> None:
    """Raise :class:`DegenerateSceneError` on non-finite or non-rigid poses; rotations within
    :data:`ROTATION_TOL` of orthonormal (rounded files) are snapped to the nearest rotation."""
    T = raw.cam_from_world
    finite = np.isfinite(T).all(axis=(1, 2))
    if not finite.all():
        i = int(np.argmin(finite))
        raise DegenerateSceneError(
            scene_id, f"image '{raw.names[i]}' has a non-finite (NaN/inf) pose; "
            f"{int((~finite).sum())} of {len(T)} poses are non-finite", raw.pose_file)
    R = T[:, :3, :3]
    err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = (err > ROTATION_TOL) | (det < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise DegenerateSceneError(
            scene_id, f"image '{raw.names[i]}' has a pose whose rotation is not a proper "
            f"rotation (|R^T R - I| = {err[i]:.2e}, tolerance {ROTATION_TOL:g}; det = "
            f"{det[i]:.3f}); {int(bad.sum())} of {len(T)} poses are off", raw.pose_file)
    fix = err > 1e-12
    if fix.any():
        # rotations printed to a few decimals (instant-ngp, hand-written files) are
        # orthonormal only to that precision: snap them to the nearest rotation (SVD)
        U, _, Vt = np.linalg.svd(R[fix])
        raw.cam_from_world = T.copy()
        raw.cam_from_world[fix, :3, :3] = U @ Vt
        raw.extras["n_rotations_orthonormalised"] = int(fix.sum())
        raw.extras["max_rotation_error"] = float(err.max())


def check_cameras(scene_id: str, raw: RawModel, undistort: bool) -> None:
    """Raise :class:`CameraModelError` on cameras the engine cannot use."""
    for name, cam in zip(raw.names, raw.cameras):
        params = np.asarray(cam.params, dtype=np.float64)
        if not np.all(np.isfinite(params)) or cam.width <= 0 or cam.height <= 0:
            raise CameraModelError(
                scene_id, f"camera of image '{name}' ({cam.model.name} {cam.width}x{cam.height}) "
                f"has invalid parameters {params.tolist()}", raw.camera_file)
        fx, fy, _, _ = pinhole_intrinsics(cam)
        if fx <= 0 or fy <= 0:
            raise CameraModelError(
                scene_id, f"camera of image '{name}' has non-positive focal length "
                f"({fx}, {fy})", raw.camera_file)
        if is_pinhole(cam):
            continue
        if not can_undistort(cam):
            raise CameraModelError(
                scene_id, f"camera model {cam.model.name} of image '{name}' cannot be mapped to "
                "a pinhole camera (spherical models are not supported)", raw.camera_file)
        if not undistort:
            raise CameraModelError(
                scene_id, f"camera model {cam.model.name} of image '{name}' has lens distortion "
                f"{params[list(cam.extra_params_idxs())].tolist()} and undistortion is off "
                "(IngestConfig.undistort=False)", raw.camera_file)


def reconcile_sizes(scene_id: str, raw: RawModel, sizes: np.ndarray, paths: list[Path]) -> int:
    """Rescale cameras to the actual image sizes (e.g. an ``images_4/`` folder).

    A camera whose image has another size but the same aspect ratio (within rounding of
    a downscale) is rescaled; a different aspect ratio is an error.

    Returns:
        Number of rescaled cameras.
    """
    n_rescaled = 0
    # One scale for the whole scene (images_4/ ...): an image whose size implies another
    # scale than the others is an outlier (a stray full-size or thumbnail file), not a
    # downscale; rescaling it would shrink the whole training set to its size.
    if len(raw.cameras) >= 3:
        cw = np.array([c.width for c in raw.cameras], np.float64)
        ch = np.array([c.height for c in raw.cameras], np.float64)
        scale = cw / np.maximum(sizes[:, 0], 1)
        s_med = float(np.median(scale))
        off = (np.abs(cw / s_med - sizes[:, 0]) > 1.0 + 1e-9) | \
              (np.abs(ch / s_med - sizes[:, 1]) > 1.0 + 1e-9)
        if off.any() and off.sum() < len(off) / 2:
            i = int(np.argmax(off))
            names = [Path(paths[k]).name for k in np.flatnonzero(off)[:5]]
            raise CameraModelError(
                scene_id, f"image size outlier: {int(off.sum())} of {len(off)} images do not "
                f"match their camera at the scene's scale 1/{s_med:g} (first {names}); "
                f"'{Path(paths[i]).name}' is {int(sizes[i, 0])}x{int(sizes[i, 1])}, its camera "
                f"{raw.cameras[i].width}x{raw.cameras[i].height} (expected "
                f"{raw.cameras[i].width / s_med:.0f}x{raw.cameras[i].height / s_med:.0f}); "
                "replace or remove the file", paths[i])
    for i, cam in enumerate(raw.cameras):
        w, h = int(sizes[i, 0]), int(sizes[i, 1])
        if (w, h) == (cam.width, cam.height):
            continue
        # a downscale by s rounds each side: |W/s - w| <= 1 with s from either side
        s = cam.width / w
        if abs(cam.height / s - h) > 1.0 + 1e-9:
            raise CameraModelError(
                scene_id, f"image is {w}x{h} but its camera ({cam.model.name}) is "
                f"{cam.width}x{cam.height}: the aspect ratio differs, so it is not a downscale",
                paths[i])
        c = copy.deepcopy(cam)
        c.rescale(w, h)
        raw.cameras[i] = c
        n_rescaled += 1
    return n_rescaled


def assemble(raw: RawModel, scene_id: str, root: Path, cfg, cache_root: Path) -> Scene:
    """Check a :class:`RawModel` and turn it into a pinhole :class:`Scene`.

    Args:
        raw: what the reader found.
        scene_id: id named in every error.
        root: the scene folder (``Scene.root``).
        cfg: :class:`schemas.ingest.IngestConfig`.
        cache_root: folder for undistorted / resized copies (``<cache_root>/undistorted``).
    Returns:
        The Scene; images in natural name order unless the reader gave a capture order.
    Raises:
        DegenerateSceneError, CameraModelError, ImageCountMismatchError, MissingInputError,
        CorruptImageError: each naming the scene and the file.
    """
    n = len(raw.names)
    if n < cfg.min_registered:
        raise DegenerateSceneError(
            scene_id, f"only {n} registered views, at least {cfg.min_registered} are needed",
            raw.pose_file)
    check_poses(scene_id, raw)
    check_cameras(scene_id, raw, cfg.undistort)
    if raw.model_names is not None:
        listed = list(raw.model_names)
        if raw.mask_paths is not None:  # masks kept among the images are not extra images
            seen = set(listed)
            for mp in raw.mask_paths:
                try:
                    rel = Path(mp).relative_to(raw.images_dir).as_posix()
                except ValueError:
                    continue
                parent = str(Path(rel).parent) if str(Path(rel).parent) != "." else ""
                in_count = raw.count_folders is None or parent in raw.count_folders
                if in_count and rel not in seen:
                    listed.append(rel)
                    seen.add(rel)
        check_image_set(scene_id, raw.images_dir, listed, raw.pose_file,
                        folders=raw.count_folders)

    # order: capture order for sequences, natural name order otherwise
    if raw.capture_order is None:
        from freescale_core.scene.images import natural_order

        order = natural_order(raw.names)
    else:
        order = np.asarray(raw.capture_order, dtype=np.int64)
    names = [raw.names[i] for i in order]
    cams = [raw.cameras[i] for i in order]
    cam_from_world = raw.cam_from_world[order]
    if raw.points_tracks is not None:  # track image indices follow the new order
        raw.points_tracks = reindex_tracks(raw.points_tracks, order, len(raw.names))
    raw.names, raw.cameras, raw.cam_from_world = names, cams, cam_from_world
    if getattr(cfg, "masks", "auto") == "ignore":
        raw.mask_paths = None
    mask_src = None if raw.mask_paths is None else [Path(raw.mask_paths[i]) for i in order]

    from freescale_core.scene.io.common import inside_scene

    src_paths = [inside_scene(scene_id, raw.images_dir, nm, "image", raw.pose_file,
                              cfg.allow_outside_paths) for nm in names]
    sizes = decode_sizes(scene_id, src_paths, check=cfg.check_images)
    n_rescaled = reconcile_sizes(scene_id, raw, sizes, src_paths)
    cams = raw.cameras
    if mask_src is not None:
        from freescale_core.scene.io.masks import check_masks

        check_masks(scene_id, mask_src, sizes, src_paths, decode=cfg.check_images)

    extras = dict(raw.extras)
    extras.update(images_dir=str(raw.images_dir), n_points=int(len(raw.points_xyz)))
    if mask_src is not None:
        extras["masks"] = raw.mask_source or "given"
    if n_rescaled:
        extras["n_rescaled_cameras"] = n_rescaled
    distorted = [not is_pinhole(c) for c in cams]
    intr = np.array([[*pinhole_intrinsics(c), c.width, c.height] for c in cams], dtype=np.float64)
    too_big = cfg.max_image_size is not None and bool(
        (np.maximum(intr[:, 4], intr[:, 5]) > cfg.max_image_size).any())

    image_paths = src_paths
    undistorted = False
    if any(distorted) or too_big:
        import pycolmap

        kind = "undistorted" if any(distorted) else "resized"
        key = fingerprint({
            "kind": kind, "names": names, "pycolmap": pycolmap.__version__,
            "cams": [[c.model.name, c.width, c.height, np.asarray(c.params).tolist()]
                     for c in cams],
            "poses": np.round(cam_from_world, 12).tolist(),
            "images": [file_stamp(p) for p in src_paths],
            "model": [file_stamp(p, content=True) for p in raw.stamp_files if p.is_file()],
            "max_image_size": cfg.max_image_size,
            **({} if mask_src is None else {"masks": [file_stamp(p) for p in mask_src]}),
        })
        folder = kind if cfg.downscale in (None, 1) and cfg.max_image_size is None else \
            f"{kind}_d{cfg.downscale or 1}_max{cfg.max_image_size or 0}"
        target = Path(cache_root) / folder
        def build(tmp: Path) -> dict:
            body = (undistort_into(tmp, names, cam_from_world, cams, raw.images_dir,
                                   cfg.max_image_size) if kind == "undistorted"
                    else resize_into(tmp, names, src_paths, intr, cfg.max_image_size))
            if mask_src is not None:  # the same pixel mapping, nearest neighbour
                from freescale_core.scene.io.masks import warp_masks_into

                body["files"] = body["files"] + warp_masks_into(
                    tmp, names, mask_src, cams, body["intrinsics"], scene_id,
                    undistort=kind == "undistorted")
            return body
        manifest, reused = build_cached_folder(target, key, build)
        intr = np.array([manifest["intrinsics"][nm] for nm in names], dtype=np.float64)
        image_paths = [target / "images" / nm for nm in names]
        if mask_src is not None:
            from freescale_core.scene.io.masks import mask_cache_name

            mask_src = [target / mask_cache_name(nm) for nm in names]
        undistorted = kind == "undistorted"
        extras.update(cache_dir=str(target), cache_reused=reused)

    cameras = Cameras(invert_pose(cam_from_world), intr[:, 0], intr[:, 1], intr[:, 2],
                      intr[:, 3], intr[:, 4].astype(np.int64), intr[:, 5].astype(np.int64))
    return Scene(
        scene_id=scene_id, root=root, image_paths=image_paths, image_names=names,
        cameras=cameras, points_xyz=raw.points_xyz, points_rgb=raw.points_rgb,
        source_format=raw.source_format, camera_models=[c.model.name for c in cams],
        undistorted=undistorted, capture_order=np.arange(n), extras=extras,
        mask_paths=mask_src, points_tracks=raw.points_tracks,
    )
