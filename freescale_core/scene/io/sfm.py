"""Structure from motion for a folder of images without poses (pycolmap, CPU).

SIFT extraction -> exhaustive or sequential matching -> incremental mapping, in a temporary
database; the largest model is kept. The model is cached atomically under
``<cache>/sfm/`` so a second ingest of the same images does not run SfM again.
"""

from __future__ import annotations

import contextlib
import shutil
import tempfile
from pathlib import Path

from freescale_core.errors import DegenerateSceneError
from freescale_core.scene.io.common import build_cached_folder, file_stamp, fingerprint

SFM_FILES = ("cameras.bin", "images.bin", "points3D.bin")


def run_sfm(scene_id: str, images_dir: Path, names: list[str], out_model_dir: Path,
            cfg) -> dict:
    """Run SfM on ``names`` (relative to ``images_dir``); write the largest model.

    Args:
        out_model_dir: folder that receives the model (``cameras.bin`` ...).
        cfg: :class:`schemas.ingest.IngestConfig` (matcher, features, seed, min_registered).
    Returns:
        Facts for the manifest: ``n_registered``, ``n_input_images``, ``n_models``.
    Raises:
        DegenerateSceneError: no model with at least ``cfg.min_registered`` images.
    """
    import pycolmap

    from PIL import Image

    from freescale_core.scene.io.undistort import quiet_colmap

    sizes = set()
    for n in names:
        with Image.open(Path(images_dir) / n) as im:
            sizes.add(im.size)
    same_size = len(sizes) == 1
    work = Path(tempfile.mkdtemp(prefix="freescale_sfm_"))
    with contextlib.ExitStack() as stack:
        stack.callback(shutil.rmtree, work, True)
        stack.enter_context(quiet_colmap(2))
        db = work / "database.db"
        ext = pycolmap.FeatureExtractionOptions()
        ext.sift.max_num_features = int(cfg.sfm_max_num_features)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        pycolmap.extract_features(
            str(db), str(images_dir), image_names=list(names),
            camera_mode=pycolmap.CameraMode.SINGLE if same_size else pycolmap.CameraMode.AUTO,
            reader_options=reader, extraction_options=ext, device=pycolmap.Device.cpu)
        if cfg.sfm_matcher == "sequential":
            pycolmap.match_sequential(str(db), device=pycolmap.Device.cpu)
        else:
            pycolmap.match_exhaustive(str(db), device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.min_model_size = int(cfg.min_registered)
        opts.random_seed = int(cfg.sfm_seed)
        opts.mapper.random_seed = int(cfg.sfm_seed)
        models = pycolmap.incremental_mapping(str(db), str(images_dir), str(work / "sparse"),
                                              options=opts)
        if not models:
            raise DegenerateSceneError(
                scene_id, f"SfM registered no model from {len(names)} images (fewer than "
                f"{cfg.min_registered} views could be registered)", images_dir)
        best = max(models.values(), key=lambda r: r.num_reg_images())
        n_reg = int(best.num_reg_images())
        if n_reg < cfg.min_registered:
            raise DegenerateSceneError(
                scene_id, f"SfM registered only {n_reg} of {len(names)} images, at least "
                f"{cfg.min_registered} are needed", images_dir)
        Path(out_model_dir).mkdir(parents=True, exist_ok=True)
        best.write(str(out_model_dir))
        return {"n_registered": n_reg, "n_input_images": len(names),
                "n_models": len(models)}


def cached_sfm(scene_id: str, images_dir: Path, names: list[str], cache_root: Path,
               cfg) -> tuple[Path, dict, bool]:
    """SfM model folder for these images, computed once and cached atomically.

    Returns:
        ``(model_dir, manifest, reused)``.
    """
    import pycolmap

    key = fingerprint({
        "kind": "sfm", "names": names, "pycolmap": pycolmap.__version__,
        "images": [file_stamp(Path(images_dir) / n) for n in names],
        "matcher": cfg.sfm_matcher, "features": cfg.sfm_max_num_features,
        "seed": cfg.sfm_seed, "min_registered": cfg.min_registered,
    })
    target = Path(cache_root) / "sfm"

    def build(tmp: Path) -> dict:
        facts = run_sfm(scene_id, images_dir, names, tmp / "sparse", cfg)
        return dict(facts, files=[f"sparse/{f}" for f in SFM_FILES])

    manifest, reused = build_cached_folder(target, key, build)
    return target / "sparse", manifest, reused
