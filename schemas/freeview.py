"""Configuration of the free-view stages (METHOD.md stages 7-10).

Defaults are the paper's numbers (or the authors' reference behaviour where the paper is
silent); every departure is named in the field's description and in ``docs/FREEVIEWS.md``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


class QualityConfig(BaseModel):
    """Stage 7 quality filter: a view passes when all three tests pass."""

    model_config = ConfigDict(extra="forbid")

    black_ratio_max: float = Field(
        0.2, ge=0.0, le=1.0,
        description="Reject when the fraction of black/empty pixels is > this (authors: 20%).",
    )
    brisque_max: float = Field(
        0.5, gt=0.0,
        description="Reject when BRISQUE/100 is >= this (paper: 0.5).",
    )
    depth_validity_min: float = Field(
        0.1, ge=0.0, le=1.0,
        description="Reject when the depth-range validity is <= this (paper: 0.1).",
    )
    crop: float = Field(
        0.7, gt=0.0, le=1.0,
        description="Side fraction of the central crop on which depth validity is computed "
                    "(paper: central 70%).",
    )
    min_valid_fraction: float = Field(
        0.1, ge=0.0, le=1.0,
        description="Depth validity is 0 when fewer than this fraction of crop pixels carry "
                    "a valid depth (authors: 10%).",
    )
    empty_alpha: float = Field(
        0.05, ge=0.0, le=1.0,
        description="pixels with accumulated alpha below this count as black / empty",
    )
    depth_alpha: float = Field(
        0.5, ge=0.0, le=1.0,
        description="a pixel's depth is valid when alpha >= this and the depth is finite and > 0",
    )


class PoseRectifyConfig(BaseModel):
    """Stage 8 pose rectification of rejected candidates."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="Try pose rectification for rejected candidates.")
    steps: list[float] = Field(
        [0.7, 0.5, 0.3],
        description="rectification steps tried in order (paper: 0.7, 0.5, 0.3), in step_unit",
    )
    step_unit: Literal["fraction", "world"] = Field(
        "fraction",
        description="fraction (scale-free: ref + s (cand - ref), slerp) or world (authors: s world "
            "units from ref)",
    )

    @field_validator("steps")
    @classmethod
    def _steps_positive(cls, v: list[float]) -> list[float]:
        if any(s <= 0 for s in v):
            raise ValueError(f"pose-rectification steps must be > 0, got {v}")
        return [float(s) for s in v]


class FinalSelectConfig(BaseModel):
    """Stage 9 final selection by stepwise BRISQUE threshold."""

    model_config = ConfigDict(extra="forbid")

    target: int = Field(100, ge=1, description="Free views wanted per scene (paper: ~100).")
    thresholds: list[float] = Field(
        [0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6],
        description="BRISQUE/100 thresholds tried in order until >= target views pass (authors: "
            "0.25 -> 0.6)",
    )
    rank_by: Literal["brisque", "trust"] = Field(
        "trust",
        description="stage-9 ranking: 'brisque' (paper) or 'trust' (predicted PSNR; ours, default)",
    )
    trust_thresholds: list[float] = Field(
        [26.0, 24.0, 22.0, 20.0, 18.0, 16.0, 14.0],
        description="Predicted-PSNR thresholds (dB) tried in order by rank_by = 'trust'.",
    )
    cap_to_target: bool = Field(
        False,
        description="keep only the target lowest-BRISQUE views once a threshold is reached (off: "
            "keep all under it)",
    )


class TrustConfig(BaseModel):
    """Per-view trust scores and the predicted PSNR (ours, issue 19;
    ``freescale_core.freeviews.trust``), and whether the filter and the final selection use
    them instead of the paper's BRISQUE rule."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        True, description="compute the trust scores of every render (needed by the trust filter and ranking)")
    filter: Literal["paper", "trust"] = Field(
        "trust",
        description="stage-7 rule: 'paper' (black, BRISQUE, depth) or 'trust' (predicted PSNR >= min_psnr)")
    min_psnr: float = Field(
        14.0, description="'trust' filter: reject views predicted below this PSNR (dB).")
    n_refs: int = Field(3, ge=0, description="Training photos warped into each view.")
    ref_max_angle_deg: float = Field(
        45.0, gt=0.0, le=180.0,
        description="max angle between the rays of a training view and the free view at a point (photos warped)")
    depth_tol: float = Field(0.03, gt=0.0, description="Relative depth tolerance of the "
                                                       "occlusion check.")
    alpha_min: float = Field(0.5, ge=0.0, le=1.0,
                             description="Pixels with alpha below this have no valid depth.")
    certain_quantile: float = Field(
        0.5, ge=0.0, lt=1.0, description="High certainty = C >= this quantile of the non-empty "
                                         "voxels (on the grid dilated by one voxel).")
    beyond_quantile: float = Field(
        0.05, ge=0.0, lt=1.0, description="A point beyond the certain region: outside the box or "
                                          "C < this quantile.")
    edge_tau: float = Field(0.1, gt=0.0, description="Depth discontinuity: relative jump > this.")
    floater_window: int = Field(15, ge=3, description="Floater test window (pixels).")
    floater_ratio: float = Field(0.6, gt=0.0, lt=1.0,
                                 description="Floater: depth < this x the window's median.")
    floater_stride: int = Field(
        1, ge=1, description="floater median on depth subsampled by this (1 = exact, as fitted)")


class ReferenceConfig(BaseModel):
    """Stage 10 reference-view selection for image rectification."""

    model_config = ConfigDict(extra="forbid")

    rule: Literal["graph", "pose"] = Field(
        "graph",
        description="reference photo: graph (highest-WIoU training neighbour, the paper) or pose "
            "(smallest pose distance)",
    )
    overlap: Literal["final_pose", "stored_graph"] = Field(
        "final_pose",
        description="graph rule: final_pose (WIoU at the rectified pose) or stored_graph (edges at "
            "NMS time)",
    )
    visibility: Literal["selection", "frustum", "occlusion"] = Field(
        "selection",
        description="Visibility rule of the 'final_pose' WIoU: the selection's (stage 5) or "
                    "a given one.",
    )
    overlap_angle_deg: tuple[float, float] | None = Field(
        (5.0, 30.0),
        description="final_pose WIoU view-direction kernel (full, zero) in degrees; None = Eq. 3 "
            "as is",
    )
    two_hop_score: Literal["product", "min"] = Field(
        "product",
        description="Score of a two-hop path v-u-t: product (default) or min of its WIoUs.",
    )
    rotation_weight: float = Field(
        1.0, ge=0.0,
        description="pose rule: distance = |dc| / L + this x angle (rad), L = median camera radius",
    )

    @field_validator("overlap_angle_deg")
    @classmethod
    def _angles_ordered(cls, v):
        if v is not None and not 0.0 <= v[0] <= v[1] <= 180.0:
            raise ValueError(f"overlap_angle_deg needs 0 <= full <= zero <= 180, got {v}")
        return v


class RectifierConfig(BaseModel):
    """Stage 10 image rectification backend."""

    model_config = ConfigDict(extra="forbid")

    backend: str = Field(
        "none",
        description="image rectifier: none (default), reproject, fixer (docs/FIXER.md), or a "
            "registered one",
    )
    params: dict[str, Any] = Field(
        default_factory=dict,
        description="Backend parameters (see freescale_core.freeviews.rectify_image for each "
            "backend).",
    )


# the fast preset's final target: its selection's NMS cap (SelectConfig.fast().nms.max_views)
FAST_TARGET = 40


class FreeViewConfig(BaseModel):
    """Stages 7-10 in one object: quality filter, pose rectification, final selection,
    reference selection and image rectification."""

    model_config = ConfigDict(extra="forbid")

    quality: QualityConfig = Field(default_factory=QualityConfig)
    pose: PoseRectifyConfig = Field(default_factory=PoseRectifyConfig)
    final: FinalSelectConfig = Field(default_factory=FinalSelectConfig)
    reference: ReferenceConfig = Field(default_factory=ReferenceConfig)
    trust: TrustConfig = Field(default_factory=TrustConfig)
    rectifier: RectifierConfig = Field(default_factory=RectifierConfig)
    render_scale: float = Field(
        1.0, gt=0.0, le=1.0,
        description="Render free views at this fraction of the candidates' resolution "
                    "(1.0 = training resolution, as the paper).",
    )
    cache_mb: float = Field(
        512.0, ge=0.0,
        description="memory (MB) for renders of passing views kept until final selection; the rest "
            "are re-rendered",
    )

    @model_validator(mode="after")
    def _thresholds_sorted(self) -> "FreeViewConfig":
        t = self.final.thresholds
        if any(b < a for a, b in zip(t, t[1:])):
            raise ValueError(f"final.thresholds must be non-decreasing, got {t}")
        t = self.final.trust_thresholds
        if any(b > a for a, b in zip(t, t[1:])):
            raise ValueError(f"final.trust_thresholds must be non-increasing, got {t}")
        if not self.trust.enabled and (self.trust.filter == "trust"
                                       or self.final.rank_by == "trust"):
            raise ValueError("trust.enabled = False needs trust.filter = 'paper' and "
                             "final.rank_by = 'brisque'")
        return self

    @classmethod
    def fast(cls) -> "FreeViewConfig":
        """Preset for tests and `make run` on a CPU: half resolution, one pose step, and a
        target of 40 views, the fast selection's NMS cap (``SelectConfig.fast``), so a fast
        run is ``scarce`` only when it falls short of what the preset asks for."""
        return cls(render_scale=0.5, pose=PoseRectifyConfig(steps=[0.5]),
                   final=FinalSelectConfig(target=FAST_TARGET))
