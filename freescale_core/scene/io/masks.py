"""Per-image object masks (turntable and object captures): finding, checking, warping.

Where masks come from:

* nerfstudio ``transforms.json``: ``frames[*].mask_path`` (relative to the json, like
  ``file_path``; with ``ingest.downscale = d`` a ``masks/`` folder is read as ``masks_<d>/``
  exactly as nerfstudio does);
* COLMAP (and bare images): a ``masks/`` folder beside ``images/`` (``masks_<d>/`` beside
  ``images_<d>/``). The mask of ``images/<sub>/<name>.<ext>`` is the first of
  ``masks/<sub>/<name>.<ext>`` (same file name), ``masks/<sub>/<name>.png`` and
  ``masks/<sub>/<name>.<ext>.png`` (COLMAP's ``ImageReader.mask_path`` convention, also what
  nerfstudio's tools write).

A mask is a single-channel image of the image's size, nonzero = object (keep), zero = ignore.
Every image has a mask or none has: a partly masked capture is a :class:`MaskError` naming how
many and which are missing (``ingest.masks=ignore`` reads no masks at all). Masks are
undistorted and resized exactly like their images, by nearest-neighbour sampling of the same
pixel mapping (COLMAP's: pixel centres at +0.5), so a mask stays binary and aligned.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath

import numpy as np

from freescale_core.errors import MaskError, MissingInputError
from freescale_core.scene.images import read_mask

def mask_dir_for(images_dir: Path) -> Path:
    """``masks/`` beside ``images/`` (``masks_4/`` beside ``images_4/``); for images kept in
    the scene folder itself, ``<folder>/masks``."""
    images_dir = Path(images_dir)
    name = images_dir.name
    if name == "images" or name.startswith("images_"):
        return images_dir.parent / ("masks" + name[len("images"):])
    return images_dir / "masks"


def _candidates(mask_dir: Path, name: str) -> list[Path]:
    p = PurePosixPath(name)
    return [mask_dir / name, mask_dir / p.with_suffix(".png").as_posix(),
            mask_dir / f"{name}.png"]


def find_folder_masks(scene_id: str, images_dir: Path, names: list[str]) -> list[Path] | None:
    """Masks of ``names`` (relative to ``images_dir``) in the masks folder beside it.

    Returns:
        ``N`` mask paths aligned with ``names``, or None when there is no masks folder.
    Raises:
        MaskError: the folder exists but some (or all) images have no mask in it.
    """
    mdir = mask_dir_for(images_dir)
    if not mdir.is_dir():
        return None
    found: list[Path | None] = []
    for nm in names:
        found.append(next((c for c in _candidates(mdir, nm) if c.is_file()), None))
    missing = [nm for nm, f in zip(names, found) if f is None]
    if missing:
        raise MaskError(
            scene_id, f"partly masked capture: {len(missing)} of {len(names)} images have no "
            f"mask in {mdir.name}/ (first {missing[:5]}; looked for the same name, <stem>.png "
            "and <name>.png); give every image a mask, or set ingest.masks=ignore to train on "
            "every pixel", mdir)
    return [Path(f) for f in found]


def check_masks(scene_id: str, mask_paths: list[Path], sizes: np.ndarray,
                image_paths: list[Path], decode: bool = True) -> None:
    """Each mask exists, decodes (when ``decode``) and has its image's size ``sizes [N, 2]``.

    Raises:
        MissingInputError, CorruptImageError, MaskError: naming the scene and the mask file.
    """
    from freescale_core.scene.io.common import header_size

    for i, mp in enumerate(mask_paths):
        if not Path(mp).is_file():
            raise MissingInputError(scene_id, f"mask of image '{Path(image_paths[i]).name}' is "
                                    "missing", mp)
        if decode:
            m = read_mask(mp, scene_id)
            w, h = m.shape[1], m.shape[0]
        else:
            w, h = header_size(scene_id, mp)
        if (w, h) != (int(sizes[i, 0]), int(sizes[i, 1])):
            raise MaskError(
                scene_id, f"mask is {w}x{h} but its image '{Path(image_paths[i]).name}' is "
                f"{int(sizes[i, 0])}x{int(sizes[i, 1])}: a mask must have its image's size", mp)


def mask_cache_name(name: str) -> str:
    """Relative path of image ``name``'s mask in a cache folder (always PNG, lossless)."""
    return f"masks/{name}" if PurePosixPath(name).suffix.lower() == ".png" else \
        f"masks/{name}.png"


def _write_mask(path: Path, m: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", np.where(m, 255, 0).astype(np.uint8))
    if not ok:
        raise RuntimeError(f"cannot encode mask {path}")
    buf.tofile(path)


def undistort_mask(mask: np.ndarray, camera, pinhole: tuple) -> np.ndarray:
    """Mask of a distorted ``camera`` (pycolmap) resampled into the pinhole camera
    ``(fx, fy, cx, cy, w, h)`` that COLMAP's undistorter made for it, by nearest neighbour.

    COLMAP's mapping: undistorted pixel ``(x, y)`` has image point ``(x + 0.5, y + 0.5)``; it is
    lifted with the pinhole camera, projected with the distorted one, and the source is read
    at that point minus 0.5 (COLMAP interpolates bilinearly there; nearest = ``floor``).
    Pixels that map outside the source are False (COLMAP fills them black)."""
    fx, fy, cx, cy, w, h = (float(v) for v in pinhole)
    w, h = int(w), int(h)
    ys, xs = np.mgrid[0:h, 0:w]
    cam = np.stack([(xs.ravel() + 0.5 - cx) / fx, (ys.ravel() + 0.5 - cy) / fy,
                    np.ones(w * h)], axis=1)
    src = np.asarray(camera.img_from_cam(cam, check_cheirality=False), np.float64)
    ix, iy = np.floor(src[:, 0]).astype(np.int64), np.floor(src[:, 1]).astype(np.int64)
    H0, W0 = mask.shape
    ok = np.isfinite(src).all(axis=1) & (ix >= 0) & (ix < W0) & (iy >= 0) & (iy < H0)
    out = np.zeros(w * h, bool)
    out[ok] = mask[iy[ok], ix[ok]]
    return out.reshape(h, w)


def resize_mask(mask: np.ndarray, w: int, h: int) -> np.ndarray:
    """Nearest-neighbour resize with pixel centres aligned (``INTER_NEAREST_EXACT``)."""
    import cv2

    if mask.shape == (h, w):
        return mask
    return cv2.resize(mask.astype(np.uint8), (int(w), int(h)),
                      interpolation=cv2.INTER_NEAREST_EXACT) > 0


def warp_masks_into(out_dir: Path, names: list[str], mask_paths: list[Path], cameras: list,
                    intrinsics: dict, scene_id: str, undistort: bool) -> list[str]:
    """Write each mask, undistorted (``undistort``) or resized to the cached image's
    intrinsics ``{name: [fx, fy, cx, cy, w, h]}``, into ``out_dir/masks/``.

    Returns:
        The written files, relative to ``out_dir``."""
    files = []
    for name, mp, cam in zip(names, mask_paths, cameras):
        m = read_mask(mp, scene_id)
        fx, fy, cx, cy, w, h = intrinsics[name]
        out = undistort_mask(m, cam, (fx, fy, cx, cy, w, h)) if undistort else \
            resize_mask(m, int(w), int(h))
        rel = mask_cache_name(name)
        _write_mask(Path(out_dir) / rel, out)
        files.append(rel)
    return files
