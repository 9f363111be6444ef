"""Configuration of the selection core (METHOD.md stages 2-6).

Defaults are the paper's numbers, or the authors' reference behaviour where the paper is
silent; every choice of ours is named in the field's description and in
``docs/SELECTION.md``. ``SelectConfig.fast()`` gives small numbers for tests and demos.

Length unit of the candidate stage ("scene scale", ``CandidateConfig.scale_unit``): by default
the median distance of the training camera centres to their centroid (``camera_radius``), so
that "sigma = 0.1" means 10% of the typical camera-to-centre distance whatever the units of
the reconstruction (COLMAP units are arbitrary).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

TRAJECTORY_MODES: tuple[str, ...] = (
    "orbit", "spiral", "lemniscate", "interpolation", "move_up", "move_down", "move_left",
    "move_right", "dolly_in", "dolly_out",
)
"""The paper's 10 trajectory modes (stage 3), in a fixed order (mode id = index)."""

Mode = Literal["orbit", "spiral", "lemniscate", "interpolation", "move_up", "move_down",
               "move_left", "move_right", "dolly_in", "dolly_out"]


def _range(lo_hi: tuple[float, float], name: str) -> tuple[float, float]:
    lo, hi = lo_hi
    if hi < lo:
        raise ValueError(f"{name}: range ({lo}, {hi}) has max < min")
    return (float(lo), float(hi))


class GridConfig(BaseModel):
    """Stage 2, Eq. 1: certainty grid over the scene box."""

    model_config = ConfigDict(extra="forbid")

    resolution: int | Literal["auto"] = Field(
        128, description="voxels per axis R (paper: 128), or auto for the scene-adaptive R")
    margin: float = Field(
        0.1, ge=0.0, description="Box = min/max of Gaussian centres widened by this fraction "
        "of its extent on each side (paper: 10%).")
    box_quantile: float = Field(
        0.005, ge=0.0, lt=0.5, description="certainty box from the q / 1-q quantiles of Gaussian "
            "centres; 0 = the paper's min/max")
    box_mass_trim: float = Field(
        0.001, ge=0.0, lt=0.5, description="set aside the least certain Gaussians holding this "
            "fraction of total certainty before the box (0 = off)")
    box_anchor_margin: float | None = Field(
        0.25, ge=0.0, description="clip the box to the cameras' and sparse points' box widened "
            "by this x its diagonal per side (None = off)")
    max_memory_gb: float | None = Field(
        None, gt=0.0, description="refuse a grid estimated above this many GB (None = half "
            "the available memory)")
    eps: float = Field(
        1e-6, gt=0.0, description="eps in alpha / (Vol + eps) (Eq. 1; the paper gives no value, "
        "ours). Vol is in world units cubed.")
    min_extent_fraction: float = Field(
        0.01, gt=0.0, description="widen a flat box axis to at least this fraction of the largest "
            "extent")
    auto_candidates: list[int] = Field(
        [32, 48, 64, 96, 128, 160, 192, 256], description="Resolutions the adaptive rule "
        "chooses from (clamped to [32, 256]).")
    auto_target_per_voxel: float = Field(
        4.0, gt=0.0, description="adaptive R: the R where the mean Gaussians per occupied voxel falls to "
            "this (log-R interpolation)")
    mask_min_fraction: float = Field(
        0.5, ge=0.0, le=1.0, description="with object masks: a Gaussian counts if inside the masks "
            "in this share of the views seeing it")

    @field_validator("resolution")
    @classmethod
    def _res(cls, v):
        if isinstance(v, int) and not (2 <= v <= 1024):
            raise ValueError(f"resolution must be in [2, 1024] or 'auto', got {v}")
        return v


class CandidateConfig(BaseModel):
    """Stage 3: candidate cameras on 10 trajectory modes around jittered anchors."""

    model_config = ConfigDict(extra="forbid")

    modes: list[Mode] = Field(list(TRAJECTORY_MODES), description="Trajectory modes to use "
                              "(paper: all 10).")
    n_traj: int = Field(10, ge=1, description="Anchors (= trajectories) per mode "
                        "(paper: N_traj = 10).")
    frames_per_traj: int = Field(20, ge=2, description="Frames per trajectory (paper: L = 20).")
    anchor_method: Literal["kmeans", "fps"] = Field(
        "kmeans", description="anchor choice among training cameras: kmeans (nearest to cluster "
            "means) or fps")
    scale_unit: Literal["camera_radius", "box_diagonal", "camera_spacing"] = Field(
        "camera_radius", description="unit of the lengths below: camera_radius, box_diagonal or "
            "camera_spacing")
    anchor_sigma: tuple[float, float] = Field(
        (0.0, 0.1), description="anchor position noise sigma range, in scene-scale units (paper: "
            "[0, 0.1])")
    anchor_rot_deg: float = Field(20.0, ge=0.0, description="Anchor rotation jitter: random "
                                  "axis, angle uniform in +-this (paper: 20 deg).")
    perturb_fraction: float = Field(
        0.2, ge=0.0, le=1.0, description="Fraction of all candidates given a random extra "
        "perturbation (the paper says 'a random subset'; 20% is ours).")
    perturb_sigma: tuple[float, float] = Field(
        (0.0, 0.5), description="Perturbation position noise sigma range, scene-scale units "
        "(paper: [0, 0.5]).")
    perturb_rot_deg: float = Field(30.0, ge=0.0, description="Perturbation rotation: random "
                                   "axis, angle uniform in +-this (paper: 30 deg).")
    orbit_arc_deg: tuple[float, float] = Field(
        (120.0, 360.0), description="Orbit arc about the up axis through the look-at point "
        "(authors: 120..360 deg).")
    orbit_radius_scale: tuple[float, float] = Field(
        (0.3, 0.6), description="orbit offset as a fraction of the anchor's distance to the "
            "look-at point (authors: 0.3..0.6)")
    spiral_turns: tuple[float, float] = Field((1.5, 3.0), description="Spiral turns "
                                              "(authors: 1.5..3).")
    spiral_radius_scale: tuple[float, float] = Field(
        (0.1, 0.3), description="spiral radius as a fraction of the anchor-to-look-at distance")
    spiral_zrate: float = Field(0.5, description="Spiral forward/backward oscillation rate "
                                "per turn (LLFF's zrate; ours).")
    lemniscate_deg: tuple[float, float] = Field(
        (30.0, 90.0), description="lemniscate total azimuth sweep (deg; authors: 30..90); "
            "elevation sweep is half")
    move_distance: tuple[float, float] = Field(
        (0.2, 0.6), description="Total translation of move_up/down/left/right trajectories, "
        "scene-scale units (ours; the paper gives none).")
    dolly_in_factor: float = Field(
        0.28, gt=0.0, description="dolly-zoom in: final/initial distance (= focal ratio) to the "
            "look-at point (authors: x0.28)")
    dolly_out_factor: float = Field(1.5, gt=0.0, description="Dolly-zoom out: same ratio "
                                    "(authors: x1.5).")
    interp_span: float = Field(
        2.0, gt=0.0, description="interpolation trajectories span +-this many training views "
            "(capture order) around the anchor")
    lookat_source: Literal["certainty", "box_center"] = Field(
        "certainty", description="look-at points: high-certainty voxels of the central region "
            "(paper) or the box centre")
    lookat_central_fraction: float = Field(
        0.5, gt=0.0, le=1.0, description="central region: voxels nearest the weighted median point "
            "holding this fraction of certainty")
    lookat_quantile: float = Field(
        0.9, ge=0.0, lt=1.0, description="High certainty = C >= this quantile of the voxels "
        "of the central region (ours).")

    @field_validator("anchor_sigma", "perturb_sigma", "orbit_arc_deg", "orbit_radius_scale",
                     "spiral_turns", "spiral_radius_scale", "lemniscate_deg", "move_distance")
    @classmethod
    def _ranges(cls, v, info):
        return _range(v, info.field_name)

    @field_validator("modes")
    @classmethod
    def _modes(cls, v):
        if len(v) == 0:
            raise ValueError("modes must not be empty")
        if len(set(v)) != len(v):
            raise ValueError(f"modes contains duplicates: {v}")
        return v


class FeasibilityConfig(BaseModel):
    """Stage 4: reject candidates outside the box or inside structure."""

    model_config = ConfigDict(extra="forbid")

    check_box: bool = Field(True, description="Reject centres outside the certainty box.")
    check_structure: bool = Field(True, description="Reject centres inside occupied voxels.")
    include_cameras: bool = Field(
        True, description="feasible region = certainty box united with the training cameras' box "
            "(ours; object-centric scenes)")
    occupancy_quantile: float = Field(
        0.25, ge=0.0, lt=1.0, description="a voxel is structure when C >= this quantile of "
            "non-empty voxels; 0 = any Gaussian")
    neighbourhood: int = Field(
        0, ge=0, le=3, description="also reject when a voxel within this Chebyshev radius is "
            "occupied (0 = the voxel itself)")


class VisibilityConfig(BaseModel):
    """Stage 5 visibility M_ik."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["frustum", "occlusion"] = Field(
        "frustum", description="frustum (the paper's rule) or occlusion (also not hidden behind "
            "occupied voxels)")
    near: float = Field(
        0.01, ge=0.0, description="Near plane, as a fraction of the certainty box diagonal.")
    zbuffer_width: int = Field(64, ge=8, description="Occlusion z-buffer width in pixels "
                               "(height follows the aspect ratio).")
    depth_margin_voxels: float = Field(
        2.0, ge=0.0, description="Occlusion: a voxel is visible when its depth <= z-buffer + "
        "this many voxel edges.")
    occluder_quantile: float = Field(
        0.25, ge=0.0, lt=1.0, description="Occlusion: voxels with C >= this quantile of the "
        "non-empty voxels occlude.")
    max_splat_radius: int = Field(6, ge=0, description="Occlusion: cap on a voxel's splat "
                                  "radius in z-buffer pixels.")


class GraphConfig(BaseModel):
    """Stage 5 view graph (and the ablations of the paper's supplement)."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["wiou", "pose_distance", "none"] = Field(
        "wiou", description="view graph: wiou (Eq. 3, the paper), pose_distance (ablation) or none "
            "(top-K by score)")
    edge_threshold: float = Field(0.01, ge=0.0, le=1.0, description="Edges need WIoU > this.")
    top_k: int = Field(16, ge=1, description="Each node keeps its top-k edges (an edge is "
                       "stored when either endpoint keeps it).")
    gemm_dtype: Literal["float32", "float64"] = Field(
        "float32", description="Precision of the Gram products I = M diag(C) M^T.")
    block_rows: int = Field(256, ge=8, description="Candidates per GEMM block in NMS.")
    bound_cells_per_axis: int = Field(
        16, ge=0, description="NMS pruning: coarse cells per axis for exact WIoU bounds (same "
            "result, faster); 0 = off")
    blas_threads: int = Field(
        1, ge=0, description="OpenBLAS threads for the NMS and graph GEMMs (0 = leave as "
            "configured)")
    pose_rot_unit_deg: float = Field(
        10.0, gt=0.0, description="pose_distance: degrees of rotation counted as one unit of "
            "centre spacing")


class NMSConfig(BaseModel):
    """Stage 6: greedy non-maximum suppression."""

    model_config = ConfigDict(extra="forbid")

    wiou_threshold: float = Field(0.7, gt=0.0, le=1.0, description="Accept a candidate when "
                                  "its WIoU with every kept view is < this (paper: 0.7).")
    pose_threshold: float = Field(3.5, gt=0.0, description="pose_distance ablation: accept "
                                  "when d >= this to every kept view (supplement: 3.5).")
    max_views: int = Field(500, ge=0, description="Stop after this many accepted candidates "
                           "(paper: K = 500).")
    min_score: float = Field(0.0, ge=0.0, description="Candidates with f <= this are never "
                             "selected (a view that sees no certain voxel is useless).")
    reserve_thresholds: list[float] = Field(
        [0.8, 0.9, 0.95, 1.0], description="relaxed NMS WIoU thresholds of the reserve drawn "
            "while short of the target (ours); [] = none")
    reserve_max: int = Field(500, ge=0, description="reserve candidates at most")

    @field_validator("reserve_thresholds")
    @classmethod
    def _reserve_increasing(cls, v: list[float]) -> list[float]:
        if any(not 0.0 < t <= 1.0 for t in v) or any(b <= a for a, b in zip(v, v[1:])):
            raise ValueError(f"reserve_thresholds must increase within (0, 1], got {v}")
        return [float(t) for t in v]


class SelectConfig(BaseModel):
    """Stages 2-6 in one object."""

    model_config = ConfigDict(extra="forbid")

    grid: GridConfig = Field(default_factory=GridConfig)
    candidates: CandidateConfig = Field(default_factory=CandidateConfig)
    feasibility: FeasibilityConfig = Field(default_factory=FeasibilityConfig)
    visibility: VisibilityConfig = Field(default_factory=VisibilityConfig)
    graph: GraphConfig = Field(default_factory=GraphConfig)
    nms: NMSConfig = Field(default_factory=NMSConfig)

    @classmethod
    def fast(cls) -> "SelectConfig":
        """Small numbers for tests and demos: R = 48, 3 trajectories x 8 frames per mode."""
        return cls(grid=GridConfig(resolution=48),
                   candidates=CandidateConfig(n_traj=3, frames_per_traj=8),
                   nms=NMSConfig(max_views=40))  # = FreeViewConfig.fast()'s final target
