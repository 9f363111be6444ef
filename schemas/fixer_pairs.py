"""Configuration of the fixer's training pairs (``freescale fixer pairs``)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field


class PairsConfig(BaseModel):
    """How the engine makes fixer training pairs from a scene (docs/FIXER.md)."""

    model_config = ConfigDict(extra="forbid")

    folds: list[Literal["every8", "ood", "oracle"]] = Field(
        ["every8", "ood", "oracle"],
        description="Held-out folds: every 8th view, the far end (last 30%), and on "
                    "procedural scenes off-path poses scored against the exact renderer.")
    budgets: list[float] = Field(
        [0.33, 1.0],
        description="Snapshots of each fold's reconstruction, as fractions of its iteration "
                    "budget (under-fitted models and the final one).")
    recon_preset: Literal["fast", "cpu", "paper"] = Field(
        "fast", description="Preset of the reconstructions that render the pairs.")
    k: int = Field(2, ge=0, le=8, description="Nearest training photos warped into each view.")
    long_side: int = Field(256, ge=16, description="Pairs are rendered with this long side.")
    max_views_per_fold: int = Field(
        12, ge=0, description="At most this many held-out views per fold (evenly spaced; 0: all).")
    oracle_views: int = Field(12, ge=1, description="Off-path poses per procedural scene.")
    threads: int = Field(0, ge=0, description="Reconstruction threads (0: all cores).")
    reproject: dict[str, Any] = Field(
        default_factory=dict,
        description="Parameters of the reproject warp (freeviews.rectify_image.ReprojectRectifier).")
