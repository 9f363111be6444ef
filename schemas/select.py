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
        128, description="Voxels per axis R (paper: 128), or 'auto' to use the scene-adaptive "
        "R (always computed and reported beside the grid).")
    margin: float = Field(
        0.1, ge=0.0, description="Box = min/max of Gaussian centres widened by this fraction "
        "of its extent on each side (paper: 10%).")
    box_quantile: float = Field(
        0.005, ge=0.0, lt=0.5, description="0 = the paper's min/max of centres; q > 0 (ours, default 0.005) = the "
        "q / 1-q quantiles of the centres (robust to far floaters; centres outside are "
        "dropped from the grid).")
    box_mass_trim: float = Field(
        0.001, ge=0.0, lt=0.5, description="Before the quantiles, set aside the least certain "
        "Gaussians that together hold this fraction of the total certainty (ours; 0 = off). "
        "Sky and background shells are large or faint, so they carry almost no certainty but "
        "can be a quarter of the Gaussians: at 3000 steps on the sample scene 26% of the "
        "centres lay beyond the objects with 0.2% of the certainty, and the quantile box "
        "alone came out 10x too wide.")
    box_anchor_margin: float | None = Field(
        0.25, ge=0.0, description="Clip the box to the training cameras and sparse points "
        "(1%/99% quantiles), widened per side by this x their box's diagonal (x8 when the "
        "scene has no sparse points). Gaussians a reconstruction threw far out then cannot "
        "stretch the box whatever certainty they carry (ours; None = off).")
    max_memory_gb: float | None = Field(
        None, gt=0.0, description="Refuse a grid whose estimated memory exceeds this (GB); "
        "None = half of the memory available when the stage starts.")
    eps: float = Field(
        1e-6, gt=0.0, description="eps in alpha / (Vol + eps) (Eq. 1; the paper gives no value, "
        "ours). Vol is in world units cubed.")
    min_extent_fraction: float = Field(
        0.01, gt=0.0, description="A flat box axis is widened to at least this fraction of "
        "the largest extent before the margin is added (ours: avoids zero-size voxels).")
    auto_candidates: list[int] = Field(
        [32, 48, 64, 96, 128, 160, 192, 256], description="Resolutions the adaptive rule "
        "chooses from (clamped to [32, 256]).")
    auto_target_per_voxel: float = Field(
        4.0, gt=0.0, description="Adaptive R: the largest candidate R at which the median "
        "number of Gaussians per occupied voxel is still >= this (ours).")

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
        "kmeans", description="How anchors are chosen among training cameras: K-Means on "
        "centres (the camera nearest each cluster mean) or farthest point sampling.")
    scale_unit: Literal["camera_radius", "box_diagonal", "camera_spacing"] = Field(
        "camera_radius", description="Unit of every length below: camera_radius = median "
        "distance of training centres to their centroid (default); box_diagonal = diagonal of "
        "the certainty box; camera_spacing = median nearest-neighbour distance of training "
        "centres. Falls back to 5% of the box diagonal when the unit is 0.")
    anchor_sigma: tuple[float, float] = Field(
        (0.0, 0.1), description="Anchor position noise N(0, sigma^2) per axis, sigma drawn "
        "uniformly from this range per anchor, in scene-scale units (paper: [0, 0.1]).")
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
        (0.3, 0.6), description="Orbit offset = this x (anchor - look-at), i.e. a fraction of "
        "the anchor's distance to the look-at point (authors' range 0.3..0.6; the reference "
        "length is our reading).")
    spiral_turns: tuple[float, float] = Field((1.5, 3.0), description="Spiral turns "
                                              "(authors: 1.5..3).")
    spiral_radius_scale: tuple[float, float] = Field(
        (0.1, 0.3), description="Spiral (LLFF-style, around the anchor in its image plane) "
        "radius as a fraction of the anchor-to-look-at distance (ours).")
    spiral_zrate: float = Field(0.5, description="Spiral forward/backward oscillation rate "
                                "per turn (LLFF's zrate; ours).")
    lemniscate_deg: tuple[float, float] = Field(
        (30.0, 90.0), description="Lemniscate (figure eight about the look-at point) total "
        "azimuth sweep (authors: 30..90 deg); elevation sweep is half of it.")
    move_distance: tuple[float, float] = Field(
        (0.2, 0.6), description="Total translation of move_up/down/left/right trajectories, "
        "scene-scale units (ours; the paper gives none).")
    dolly_in_factor: float = Field(
        0.28, gt=0.0, description="Dolly-zoom in: final/initial distance to the look-at point "
        "= final/initial focal length, so the target keeps its image size (authors: x0.28).")
    dolly_out_factor: float = Field(1.5, gt=0.0, description="Dolly-zoom out: same ratio "
                                    "(authors: x1.5).")
    interp_span: float = Field(
        2.0, gt=0.0, description="Interpolation trajectories cover +-this many training views "
        "(in capture order) around the anchor on a cubic spline (ours).")
    lookat_source: Literal["certainty", "box_center"] = Field(
        "certainty", description="Look-at points of object-centric modes: sampled from "
        "high-certainty voxels of the central region (paper), or the box centre (ablation).")
    lookat_central_fraction: float = Field(
        0.5, gt=0.0, le=1.0, description="Central region = the non-empty voxels nearest to the "
        "certainty-weighted median point that hold this fraction of the total certainty "
        "(ours; robust to far floaters, never empty).")
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
        True, description="The feasible region is the certainty box united with the box of "
        "the training camera centres (widened by the grid margin). Ours: for object-centric "
        "captures the cameras stand outside the Gaussians' box, and the paper's rule then "
        "rejects nearly every candidate (216 of 240 on kermit).")
    occupancy_quantile: float = Field(
        0.25, ge=0.0, lt=1.0, description="A voxel is occupied (structure) when C >= this "
        "quantile of the non-empty voxels' C; 0 = any voxel holding a Gaussian (ours: ignores "
        "the faintest floaters).")
    neighbourhood: int = Field(
        0, ge=0, le=3, description="Also reject when any voxel within this Chebyshev radius of "
        "the centre's voxel is occupied (0 = the voxel itself).")


class VisibilityConfig(BaseModel):
    """Stage 5 visibility M_ik."""

    model_config = ConfigDict(extra="forbid")

    mode: Literal["frustum", "occlusion"] = Field(
        "frustum", description="frustum = the paper's rule (voxel centre projects inside the "
        "image with z > near); occlusion = additionally not hidden behind occupied voxels "
        "(per-camera low-resolution z-buffer of occupied voxels).")
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
        "wiou", description="wiou = certainty-weighted IoU (Eq. 3, the paper); pose_distance = "
        "no certainty grid in the graph (ablation); none = no view graph, top-K by score "
        "(ablation).")
    edge_threshold: float = Field(0.01, ge=0.0, le=1.0, description="Edges need WIoU > this.")
    top_k: int = Field(16, ge=1, description="Each node keeps its top-k edges (an edge is "
                       "stored when either endpoint keeps it).")
    gemm_dtype: Literal["float32", "float64"] = Field(
        "float32", description="Precision of the Gram products I = M diag(C) M^T.")
    block_rows: int = Field(256, ge=8, description="Candidates per GEMM block in NMS.")
    bound_cells_per_axis: int = Field(
        16, ge=0, description="NMS pruning: coarse cells per axis for the exact lower/upper "
        "bounds of WIoU (pairs the bounds decide skip the voxel-level GEMM; the result is "
        "identical). 0 = no bounds, every pair in the score window is computed.")
    blas_threads: int = Field(
        1, ge=0, description="OpenBLAS threads for the NMS and graph GEMMs (0 = leave as "
        "configured). 1 by default: these GEMMs gain little from threads on 2 cores and "
        "multi-threaded OpenBLAS spin-waits badly when processes share the cores.")
    pose_rot_unit_deg: float = Field(
        10.0, gt=0.0, description="pose_distance: d = |c_i - c_j| / s + angle(R_i, R_j) / "
        "this, s = median nearest-neighbour spacing of training centres (ours; the "
        "supplement gives only the threshold).")


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
                   nms=NMSConfig(max_views=40))
