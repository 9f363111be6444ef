"""Configuration of scene ingestion (before METHOD.md stage 1: the scene every stage reads).

The paper pre-filters its input scenes (image count must match the camera model, images must
decode, at least a few registered views, finite poses) and works on pinhole images with COLMAP
poses; these fields control how a scene folder becomes that pinhole ``Scene``.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class IngestConfig(BaseModel):
    """How :func:`freescale_core.scene.io.load_scene` turns a scene folder into a pinhole ``Scene``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    format: Literal["auto", "colmap", "nerfstudio", "images"] = Field(
        "auto",
        description="Input format. 'auto' detects it: transforms.json -> nerfstudio; a "
        "sparse/ model (sparse/0, sparse, or model files in the folder) -> colmap; image files "
        "directly in the folder -> images (SfM is run). A folder with images/ but no model is "
        "rejected unless 'images' is asked for explicitly.",
    )
    downscale: int | None = Field(
        None, ge=1,
        description="Read the pre-downscaled images of the images_<d>/ folder (d = 2, 4, 8 in "
        "nerfstudio / Mip-NeRF 360 layouts); intrinsics are scaled to the actual image size. "
        "None or 1 reads images/.",
    )
    undistort: bool = Field(
        True,
        description="Undistort images of cameras with lens distortion into pinhole images "
        "(cached). When False, a distorted camera model is rejected with CameraModelError.",
    )
    max_image_size: int | None = Field(
        None, ge=16,
        description="If set, images whose longer side exceeds this many pixels are resized "
        "down (cached copies, intrinsics scaled). None keeps the input resolution.",
    )
    sfm_matcher: Literal["exhaustive", "sequential"] = Field(
        "exhaustive",
        description="Feature matcher for a folder of images without poses: 'exhaustive' "
        "(all pairs; best for unordered photos up to a few hundred) or 'sequential' "
        "(neighbouring frames in name order; for video frames).",
    )
    sfm_max_num_features: int = Field(
        8192, ge=64, description="SIFT features per image for SfM (COLMAP's default)."
    )
    sfm_seed: int = Field(0, description="Random seed of the SfM mapper (determinism).")
    min_registered: int = Field(
        3, ge=2,
        description="Fewer registered views than this -> DegenerateSceneError (the paper's "
        "pre-filter; 3 is the least that constrains a 3D reconstruction).",
    )
    allow_outside_paths: bool = Field(
        False,
        description="Let the model name files outside the scene folder (a transforms.json "
        "file_path or ply_file_path with '..' or an absolute path, a COLMAP image name with "
        "'..'). Off: such a scene fails with UnsafePathError naming the frame and the path.",
    )
    check_images: bool = Field(
        True,
        description="Decode every image once at ingest so corrupt or truncated files fail "
        "here, naming the file, rather than deep inside a later stage.",
    )
