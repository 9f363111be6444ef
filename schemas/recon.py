"""Configuration of the reconstruction stage (METHOD.md stage 1: 3D Gaussians from images).

Defaults are the paper's numbers (30k iterations, densify 500..25k every 500, MCMC, cap 1.5M,
opacity init 0.5, SH degree 3, lambda_ssim 0.2) and the 3DGS learning rates. The *adaptive*
fields decide, per scene, how much model the scene needs (training resolution, Gaussian budget,
when to stop); ``docs/RECON.md`` explains each rule and the numbers behind its defaults.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class ReconConfig(BaseModel):
    """Per-scene 3D Gaussian reconstruction (METHOD.md stage 1)."""

    model_config = ConfigDict(extra="forbid")

    # ------------------------------------------------------------------ schedule (paper)
    max_iterations: int = Field(
        30_000, ge=1, description="upper bound on optimisation steps (paper: 30k); the plateau "
            "rule usually stops earlier")
    min_iterations: int = Field(
        1_000, ge=0, description="The plateau rule is not consulted before this step.")
    densify_from: int = Field(500, ge=0, description="First densification step (paper: 500).")
    densify_until: int = Field(25_000, ge=0, description="Last densification step (paper: 25k).")
    densify_every: int = Field(500, ge=1, description="Steps between densifications (paper: 500).")
    densify: Literal["mcmc", "none"] = Field(
        "mcmc", description="densification: mcmc (3DGS-MCMC relocation + growth to the budget, the "
            "paper's) or none")
    cap_gaussians: int = Field(
        1_500_000, ge=1, description="Hard ceiling on the Gaussian count (paper: 1.5M). The "
        "per-scene budget (below) is usually far lower.")
    opacity_init: float = Field(0.5, gt=0.0, lt=1.0, description="Initial opacity (paper: 0.5).")
    random_init_points: int = Field(
        10000, ge=4, description="random initial points in the cameras' view volume when a scene has no sparse points")
    init_points: Literal["train", "all"] = Field(
        "train", description="sparse points to start from: those >= 2 training views made (train), or all (incl. held-out views')")
    init_triangulate_below: float | None = Field(
        None, gt=0, description="add SIFT points triangulated from the training views when sparse points per view < this")
    init_triangulate_min_views: int = Field(
        2, ge=2, le=16, description="keep a triangulated point only when at least this many training views observe it")
    sh_degree: int = Field(3, ge=0, le=3, description="Final spherical-harmonics degree.")
    sh_views_per_coeff: float | None = Field(
        None, gt=0, description="cap the SH degree at the largest d with this x (d+1)^2 <= training views (>= 1); None: off")
    sh_cap_min_gain_std: float | None = Field(
        None, ge=0, description="apply sh_views_per_coeff only where the views' log colour gains spread more than this; None: always")
    sh_increase_every: int = Field(
        1_000, ge=1, description="Raise the active SH degree by one every this many steps (3DGS).")
    lambda_ssim: float = Field(
        0.2, ge=0.0, le=1.0, description="Loss = (1 - lambda) L1 + lambda (1 - SSIM) (3DGS).")
    background: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="Background colour composited behind the Gaussians.")
    background_lr: float | None = Field(
        None, gt=0, description="learn the background colour (from `background`) at this Adam rate; renders use it; None: fixed")
    background_min_uncovered: float | None = Field(
        None, ge=0, le=1, description="keep the learned colour only if this share of training pixels is below alpha 0.5 by background_gate_step")
    background_gate_step: int = Field(
        500, ge=2, description="the step K at which background_min_uncovered decides (share over steps K/2..K; else background, fixed)")
    background_lr_final: float | None = Field(
        None, gt=0, description="the learned colour's rate decays exponentially to this along the means' schedule; None: constant")
    batch_views: int = Field(
        1, ge=1, le=8, description="views per optimiser step (losses averaged; lr x sqrt(B), Adam betas 1-B(1-b)); schedules count steps")
    masked_pixels: Literal["background", "ignore"] = Field(
        "background", description="pixels outside a capture's object masks: trained toward background "
            "(clean object) or ignore (no loss)")

    # ------------------------------------------------------------------ Adam (3DGS rates)
    lr_means_init: float = Field(1.6e-4, gt=0, description="Means lr at step 0, times the scene "
                                 "extent (3DGS position_lr_init).")
    lr_means_final: float = Field(1.6e-6, gt=0, description="Means lr at the end of the schedule, "
                                  "times the scene extent (3DGS position_lr_final).")
    lr_sh_dc: float = Field(2.5e-3, gt=0, description="lr of the SH DC term (3DGS feature_lr).")
    lr_sh_rest: float = Field(2.5e-3 / 20, gt=0,
                              description="lr of higher SH terms (feature_lr / 20).")
    lr_opacity: float = Field(0.05, gt=0, description="lr of opacity logits (3DGS).")
    lr_scales: float = Field(5e-3, gt=0, description="lr of log-scales (3DGS).")
    lr_quats: float = Field(1e-3, gt=0, description="lr of quaternions (3DGS).")

    # ------------------------------------------------------------------ MCMC (3DGS-MCMC)
    mcmc_min_opacity: float = Field(
        0.005, gt=0, lt=1, description="Gaussians at or below this opacity are dead and relocated.")
    mcmc_growth: float = Field(
        1.05, ge=1.0, description="Minimum growth factor of the count per densification "
        "(MCMC: 5%).")
    mcmc_grow_steps: int = Field(
        20, ge=1, description="reach the Gaussian budget within this many densifications (growth "
            "factor raised if needed)")
    mcmc_noise_lr: float = Field(5e5, ge=0, description="Position noise scale (MCMC lambda_noise).")
    mcmc_opacity_reg: float = Field(0.01, ge=0, description="Weight of mean opacity (MCMC).")
    mcmc_scale_reg: float = Field(0.01, ge=0, description="Weight of mean scale (MCMC).")
    mcmc_max_copies: int = Field(51, ge=2, description="At most this many Gaussians share one "
                                 "source in one relocation (MCMC n_max).")

    # ------------------------------------------------------------------ keeping Gaussians in
    bounds_every: int = Field(
        100, ge=0, description="every this many steps relocate Gaussians out of the bound or caught "
        "by a prune_* rule (0: none of these run)")
    bounds_quantile: float = Field(
        0.02, ge=0, lt=0.5, description="The scene bound spans the camera centres and this "
        "lower/upper per-axis quantile of the sparse points.")
    bounds_margin: float | None = Field(
        3.0, gt=0, description="relocate Gaussians farther than this many bound radii from the bound's centre (None: off)")
    prune_min_views: int | None = Field(
        None, ge=1, description="relocate Gaussians whose centre fewer than this many training views see (None: off)")
    prune_min_views_size: float | None = Field(
        None, gt=0, description="prune_min_views only for Gaussians larger than this many times the median (None: any)")

    # ------------------------------------------------------------------ adaptive sizing
    max_long_side: int = Field(
        1_600, ge=8, description="Training images are downscaled so their long side is at most "
        "this (3DGS rescales inputs wider than 1.6K).")
    detail_psnr_db: float | None = Field(
        35.0, description="resolution rule: downscale while every probed image's down-up round "
            "trip keeps this PSNR (dB)")
    detail_factors: tuple[int, ...] = Field(
        (2, 4), description="Candidate integer downscale factors for the detail test.")
    budget_per_point: float = Field(
        10.0, ge=0, description="Budget rule: Gaussians per sparse SfM point (3DGS ends with "
        "~10-30x the SfM count).")
    budget_pixels_per_gaussian: float = Field(
        40.0, gt=0, description="Gaussian budget: one Gaussian per this many training pixels")
    budget_min: int = Field(1_000, ge=1, description="Budget floor for tiny scenes.")
    plateau_ema_halflife: float = Field(
        50.0, gt=0, description="Half-life (steps) of the loss EMA; raised to 2 epochs of the "
        "training views so every view is in the average.")
    plateau_window: int = Field(
        1_000, ge=1, description="plateau rule: compare the loss EMA with its value this many "
            "steps earlier")
    plateau_tol: float = Field(
        0.01, ge=0, description="plateau when the loss EMA improved by less than this fraction "
            "over the window")
    anneal_fraction: float = Field(
        0.1, ge=0, description="final annealing phase length, as a fraction of the steps so far")
    max_seconds: float | None = Field(
        None, gt=0, description="wall-clock budget of the training loop (s); annealing starts in "
            "time to end by it; None: no limit")

    coarse_to_fine: tuple[tuple[int, int], ...] = Field(
        (), description="((until_step, factor), ...): train on views downscaled by factor before until_step")

    # ------------------------------------------------------------------ evaluation/runtime
    train_eval_views: int = Field(
        32, ge=1, description="recon_train_psnr is the mean over at most this many training views "
        "(evenly spaced).")
    raster_backend: Literal["auto", "cpu", "gsplat", "reference"] = Field(
        "auto", description="rasterizer: auto (gsplat on CUDA, else numba CPU kernels), or "
            "reference (slow dense oracle)")
    threads: int | None = Field(
        None, ge=1, description="numba threads of the rasterizer during training (None: all "
        "cores); restored afterwards.")
    torch_threads: int = Field(
        1, ge=1, description="torch intra-op threads during training (restored afterwards); 1 is "
            "fastest on a shared 2-core CPU")
    nan_check_every: int = Field(50, ge=1, description="Check parameters for NaN/inf every this "
                                 "many steps (the loss is checked every step).")

    # ------------------------------------------------------------------ presets
    @classmethod
    def fast(cls) -> "ReconConfig":
        """Tests and demos: a few hundred steps on small images with a small budget."""
        return cls(
            max_iterations=300, min_iterations=60,                  # a few hundred steps
            densify_from=50, densify_until=250, densify_every=50,
            sh_degree=1, sh_increase_every=100,
            max_long_side=128, detail_psnr_db=None,                 # small images, no detail test
            budget_min=200, budget_pixels_per_gaussian=40.0, cap_gaussians=5_000,
            plateau_ema_halflife=10.0, plateau_window=60, plateau_tol=0.02,
            mcmc_grow_steps=4, nan_check_every=10, train_eval_views=8, bounds_every=50)

    @classmethod
    def cpu(cls) -> "ReconConfig":
        """This project's CPU default: the paper's rules on smaller images, a compressed
        schedule and a 10-minute budget. Why each setting: CHANGELOG.md (lab/results/)."""
        return cls(
            max_iterations=15_000, min_iterations=1_000,             # schedule compressed 5x
            densify_from=200, densify_until=10_000, densify_every=100,
            sh_increase_every=500,
            max_long_side=512,                                      # long side <= 512 px
            plateau_window=500, plateau_ema_halflife=50.0,
            mcmc_grow_steps=15,
            max_seconds=600.0,                                      # 10 min; annealing from 9.1
            coarse_to_fine=((250, 4), (600, 2)),                    # 1/4 then 1/2 size first
            init_triangulate_below=400.0,                           # thin sparse models: + SIFT points
            bounds_margin=10.0,                                     # escape bound: 10 radii
            prune_min_views=2, prune_min_views_size=10.0,           # large Gaussians < 2 views see
            background_lr=0.01, background_lr_final=1e-4,           # learned background colour,
            background_min_uncovered=0.005,                         # kept if it covers >= 0.5%
            sh_views_per_coeff=2.0, sh_cap_min_gain_std=0.05)       # SH cap where exposure varies
