"""Scene ingestion: any supported scene folder -> the checked, pinhole :class:`Scene`.

Formats (detected by :func:`detect_format`):

* ``colmap``: a COLMAP sparse model (``sparse/0/``, ``sparse/`` or the folder itself; binary
  or text) with ``images/`` beside ``sparse/``;
* ``nerfstudio``: a ``transforms.json`` (nerfstudio / DL3DV), with optional ``images_<d>/``;
* ``images``: a folder of images only; SfM is run here (pycolmap, CPU).

Object masks (nerfstudio ``mask_path``, a ``masks/`` folder beside ``images/``) are read by
:mod:`freescale_core.scene.io.masks` into ``Scene.mask_paths`` (``ingest.masks``).

The paper's input pre-filter is applied by every reader and each failure is a
:class:`~freescale_core.errors.SceneError` subclass naming the scene and the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from freescale_core.errors import MissingInputError
from freescale_core.scene.scene import Scene
from freescale_core.scene.io.common import CorruptModelError, MissingImageError, default_cache_root, list_images

__all__ = ["load_scene", "detect_format", "SceneSource", "CorruptModelError",
           "MissingImageError"]


@dataclass
class SceneSource:
    """Where a scene's parts are.

    Attributes:
        format: ``colmap``, ``nerfstudio`` or ``images``.
        root: the scene folder (its name is the default scene id).
        model_path: COLMAP model folder, transforms.json file, or None (images).
        images_dir: folder of the images (COLMAP / images); for nerfstudio the json's folder.
    """

    format: str
    root: Path
    model_path: Path | None
    images_dir: Path


def _scene_root_of_model_dir(folder: Path) -> Path:
    """``scene`` for ``scene/sparse/0`` or ``scene/sparse``; else the folder itself."""
    if folder.parent.name == "sparse":
        return folder.parent.parent
    if folder.name == "sparse":
        return folder.parent
    return folder


def detect_format(path: str | Path, fmt: str = "auto", scene_id: str | None = None,
                  downscale: int | None = None) -> SceneSource:
    """Find the format and the parts of the scene at ``path``.

    Args:
        path: scene folder, a COLMAP model folder, or a transforms.json file.
        fmt: ``auto`` or a format to force.
        downscale: look for ``images_<d>/`` instead of ``images/`` (COLMAP layout).
    Raises:
        MissingInputError: nothing usable at ``path`` (e.g. ``images/`` but no ``sparse/``).
    """
    from freescale_core.scene.io.colmap import find_model_dir, has_model_files

    path = Path(path)
    sid = scene_id or (path.parent.name if path.is_file() else path.name) or str(path)
    if not path.exists():
        raise MissingInputError(sid, "scene path does not exist", path)
    if path.is_file():
        if path.suffix.lower() == ".json":
            return SceneSource("nerfstudio", path.parent, path, path.parent)
        raise MissingInputError(sid, "expected a scene folder or a transforms.json file", path)

    def images_folder(root: Path) -> Path:
        name = f"images_{downscale}" if downscale and downscale > 1 else "images"
        return root / name

    if fmt in ("auto", "nerfstudio") and (path / "transforms.json").is_file():
        return SceneSource("nerfstudio", path, path / "transforms.json", path)
    if fmt == "nerfstudio":
        raise MissingInputError(sid, "no transforms.json in the scene folder",
                                path / "transforms.json")
    if fmt in ("auto", "colmap"):
        if has_model_files(path):
            root = _scene_root_of_model_dir(path)
            imgs = images_folder(root)
            if not imgs.is_dir() and images_folder(path).is_dir():
                imgs = images_folder(path)
            return SceneSource("colmap", root, path, imgs)
        model_dir = find_model_dir(path)
        if model_dir is not None:
            return SceneSource("colmap", path, model_dir, images_folder(path))
    if fmt == "images":
        imgs = path / "images" if (path / "images").is_dir() else path
        return SceneSource("images", path, None, imgs)
    if fmt == "auto" and list_images(path, recursive=False):
        return SceneSource("images", path, None, path)
    if (path / "sparse").is_dir():
        raise MissingInputError(sid, "sparse/ holds no COLMAP model (cameras, images, "
                                "points3D .bin or .txt)", path / "sparse")
    if (path / "images").is_dir():
        raise MissingInputError(
            sid, "no camera model: missing sparse/ folder (COLMAP) and transforms.json beside "
            "images/; to run SfM on the images pass IngestConfig(format='images')",
            path / "sparse")
    raise MissingInputError(sid, "no scene found: expected sparse/ (COLMAP), transforms.json "
                            "or image files", path)


def load_scene(path: str | Path, scene_id: str | None = None,
               cache_dir: str | Path | None = None, cfg=None) -> Scene:
    """Read any supported scene into a checked, pinhole :class:`Scene` (input of stage 1).

    Args:
        path: scene folder (or a COLMAP model folder, or a transforms.json file).
        scene_id: id used in errors and caches; default: the scene folder's name.
        cache_dir: where undistorted / resized images and SfM models are cached
            (``<cache_dir>/<scene_id>/``); default ``<scene>/.freescale_cache/`` (or a temp
            folder when the scene folder is read-only).
        cfg: :class:`schemas.ingest.IngestConfig`; defaults when None.
    Returns:
        The Scene. ``extras`` records ``format`` facts (``n_registered``, ``n_input_images``
        for SfM, ``applied_transform`` for nerfstudio, ``cache_dir``, ``cache_reused``).
    Raises:
        MissingInputError, CorruptImageError, CameraModelError, ImageCountMismatchError,
        DegenerateSceneError, CorruptModelError: all :class:`SceneError`, naming scene + file.
    """
    from schemas.ingest import IngestConfig

    from freescale_core.scene.io.assemble import assemble

    cfg = cfg or IngestConfig()
    src = detect_format(path, cfg.format, scene_id, cfg.downscale)
    sid = scene_id or src.root.name
    cache_root = default_cache_root(src.root, sid, None if cache_dir is None else Path(cache_dir))

    if src.format == "colmap":
        from freescale_core.scene.io.colmap import read_colmap_raw

        if not src.images_dir.is_dir():
            raise MissingInputError(sid, f"image folder {src.images_dir.name}/ is missing "
                                    "beside the COLMAP model", src.images_dir)
        raw = read_colmap_raw(sid, src.model_path, src.images_dir)
    elif src.format == "nerfstudio":
        from freescale_core.scene.io.nerfstudio import read_transforms_raw

        raw = read_transforms_raw(sid, src.model_path, cfg.downscale,
                                  allow_outside=cfg.allow_outside_paths,
                                  read_masks=cfg.masks != "ignore")
    else:
        from freescale_core.scene.io.colmap import raw_from_reconstruction, read_reconstruction
        from freescale_core.scene.io.common import decode_sizes
        from freescale_core.scene.io.sfm import cached_sfm

        names = list_images(src.images_dir, recursive=src.images_dir != src.root)
        if len(names) < cfg.min_registered:
            from freescale_core.errors import DegenerateSceneError

            raise DegenerateSceneError(sid, f"only {len(names)} images, at least "
                                       f"{cfg.min_registered} are needed for SfM",
                                       src.images_dir)
        # corrupt inputs fail here, naming the file, not as silently skipped SfM images
        decode_sizes(sid, [src.images_dir / n for n in names], check=cfg.check_images)
        model_dir, manifest, reused = cached_sfm(sid, src.images_dir, names, cache_root, cfg)
        rec = read_reconstruction(sid, model_dir)
        raw = raw_from_reconstruction(sid, rec, model_dir, src.images_dir, check_counts=False)
        raw.source_format = "images"
        raw.extras.update(n_registered=int(manifest["n_registered"]),
                          n_input_images=int(manifest["n_input_images"]),
                          unregistered=sorted(set(names) - set(raw.names)),
                          sfm_cache_reused=reused)
    raw.extras["format"] = src.format
    if src.format != "nerfstudio" and cfg.masks != "ignore":
        from freescale_core.scene.io.masks import find_folder_masks, mask_dir_for

        raw.mask_paths = find_folder_masks(sid, raw.images_dir, raw.names)
        if raw.mask_paths is not None:
            raw.mask_source = f"{mask_dir_for(raw.images_dir).name}/"
    scene = assemble(raw, sid, src.root, cfg, cache_root)
    read_heldout_list(scene, src.root / HELDOUT_LIST)
    return scene


HELDOUT_LIST = "heldout.txt"


def read_heldout_list(scene: Scene, path: Path) -> None:
    """A scene folder's ``heldout.txt`` (one image name per line, as the model names it;
    ``#`` comments): these views are the held-out views of ``recon_split`` ``ood`` /
    ``every8`` instead of the split rule (``Scene.extras["heldout_names"]``). Used by the
    evaluation's derived real scenes (fewer training views, same held-out views)."""
    if not path.is_file():
        return
    from freescale_core.errors import DegenerateSceneError

    names = [ln.strip() for ln in path.read_text().splitlines()
             if ln.strip() and not ln.lstrip().startswith("#")]
    unknown = sorted(set(names) - set(scene.image_names))
    if unknown:
        raise MissingInputError(scene.scene_id, f"{len(unknown)} held-out image(s) listed in "
                                f"{path.name} are not in the scene: {unknown[:3]}", path)
    if not names or len(set(names)) >= len(scene):
        raise DegenerateSceneError(scene.scene_id, f"{path.name} must list at least one view "
                                   f"and leave one to train on ({len(set(names))} of "
                                   f"{len(scene)} listed)", path)
    scene.extras["heldout_names"] = list(dict.fromkeys(names))
