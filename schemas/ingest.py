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
        description="input format; auto: transforms.json -> nerfstudio, sparse/ model -> colmap, "
            "bare images -> images (SfM)",
    )
    downscale: int | None = Field(
        None, ge=1,
        description="read images_<d>/ (d = 2, 4, 8) instead of images/; intrinsics follow the "
            "image size; None or 1: images/",
    )
    undistort: bool = Field(
        True,
        description="undistort distorted camera models to pinhole (cached); False rejects them "
            "(CameraModelError)",
    )
    max_image_size: int | None = Field(
        None, ge=16,
        description="resize images whose longer side exceeds this (px; cached, intrinsics scaled); "
            "None keeps the size",
    )
    sfm_matcher: Literal["exhaustive", "sequential"] = Field(
        "exhaustive",
        description="SfM matcher for images without poses: exhaustive (unordered photos) or "
            "sequential (video frames)",
    )
    sfm_max_num_features: int = Field(
        8192, ge=64, description="SIFT features per image for SfM (COLMAP's default)."
    )
    sfm_seed: int = Field(0, description="Random seed of the SfM mapper (determinism).")
    min_registered: int = Field(
        3, ge=2,
        description="fewer registered views than this -> DegenerateSceneError (the paper's "
            "pre-filter)",
    )
    allow_outside_paths: bool = Field(
        False,
        description="let the camera model name files outside the scene folder ('..', absolute "
        "paths); off: UnsafePathError",
    )
    check_images: bool = Field(
        True,
        description="decode every image at ingest so a corrupt file fails here, naming the file",
    )
    masks: Literal["auto", "ignore"] = Field(
        "auto",
        description="object masks: auto (read mask_path, or masks/ beside images/, when present) or "
            "ignore (read none)",
    )
