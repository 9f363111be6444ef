"""Configuration of the fixer network and its training (``freescale_core.fixer``; issue 60).

Two configs:

* ``FixerModelConfig``: the U-Net (``freescale_core.fixer.model``). Input: the render, its
  alpha and ``k`` warped nearby photos with their weights (``4 + 4k`` channels, see
  ``freescale_core.fixer.data.model_input``); output: the corrected image and a per-pixel
  confidence. The default (k=2, 4 levels, 16 base channels, a half-resolution stem, the blend
  head) is the shipped checkpoint's (docs/FIXER.md: how it was chosen and what it costs).
* ``FixerTrainConfig``: the cross-scene training run (``freescale_core.fixer.train``): a step
  budget and/or a CPU-seconds budget, random patches, loss weights, checkpoints.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class FixerModelConfig(BaseModel):
    """Residual U-Net: ``levels`` resolutions, channels ``base * 2**i`` at level ``i``."""

    model_config = ConfigDict(extra="forbid")

    k: int = Field(2, ge=0, description="Warped nearby photos in the input (0 = render only).")
    levels: int = Field(4, ge=1, le=6, description="Resolutions of the U-Net (levels - 1 "
                        "stride-2 downsamplings; inputs are reflect-padded to a multiple of "
                        "unshuffle * 2**(levels - 1) and cropped back).")
    base_channels: int = Field(16, ge=4, description="Channels at full resolution; doubled "
                               "at every level below.")
    blocks: int = Field(1, ge=1, description="Residual blocks (conv-act-conv + skip) per level "
                        "on each side.")
    unshuffle: int = Field(2, ge=1, le=4, description="Space-to-depth factor of the stem: the "
                           "U-Net runs at 1/unshuffle of the resolution on unshuffle**2 times "
                           "the channels and the head shuffles back (2: about 3x cheaper than 1 "
                           "in CPU time, but 4 x 12 input channels meet 16 features).")
    norm: str = Field("none", pattern="^(none|group)$",
                      description="'none' or 'group' (GroupNorm, 4 groups) inside the blocks.")
    head: str = Field("blend", pattern="^(residual|blend)$",
                      description="'residual': fixed = render + a predicted change; 'blend': "
                      "fixed = a per-pixel softmax mix of the render and the valid warped "
                      "photos (a warp's logit gets log of its weight; 0 weight = excluded), "
                      "plus a predicted change.")

    @property
    def in_channels(self) -> int:
        return 4 + 4 * self.k


class FixerTrainConfig(BaseModel):
    """One cross-scene fixer training run (defaults: a CPU run of a few minutes)."""

    model_config = ConfigDict(extra="forbid")

    model: FixerModelConfig = Field(default_factory=FixerModelConfig)
    seed: int = Field(0, description="Model init and patch draws: same seed, pairs and config "
                      "-> the same weights.")
    init_from: str | None = Field(
        None, description="Start from this fixer checkpoint's weights (fixer.pt; its model "
        "config must equal `model`) instead of a random init: per-scene fine-tuning "
        "(test-time adaptation) on a target scene's own leave-out pairs, with --train SCENE.")
    steps: int = Field(1000, ge=1, description="Optimiser steps (the step budget).")
    max_cpu_seconds: float | None = Field(
        None, gt=0, description="Stop earlier once the run has used this many CPU seconds "
        "(process CPU time, summed over resumes); None = steps only. A run stopped by it is "
        "not bit-reproducible (the step it stops at depends on the machine).")
    batch_size: int = Field(8, ge=1, description="Patches per step.")
    patch: int = Field(64, ge=16, description="Square patch side in pixels (cut to the "
                       "smallest pair's side when larger).")
    lr: float = Field(2e-3, gt=0, description="AdamW peak learning rate.")
    weight_decay: float = Field(0.0, ge=0, description="AdamW weight decay.")
    warmup_steps: int = Field(50, ge=0, description="Linear warmup; then cosine to "
                              "min_lr_ratio * lr at `steps`.")
    min_lr_ratio: float = Field(0.1, ge=0, le=1, description="Final lr / peak lr.")
    grad_clip: float = Field(1.0, gt=0, description="Max global gradient norm.")
    lambda_ssim: float = Field(0.2, ge=0, le=1, description="Image loss (1-l) L1 + l (1-SSIM) "
                               "over the mask (the recon loss).")
    lambda_conf: float = Field(0.05, ge=0, description="Weight of the confidence term: BCE of "
                               "the confidence against exp(-|e| / conf_tau), e the detached "
                               "per-pixel error of the corrected image.")
    conf_tau: float = Field(0.05, gt=0, description="Error scale of the confidence target: "
                            "confidence 0.5 ~ a mean abs error of tau ln 2.")
    flip: bool = Field(True, description="Random horizontal flip of every input and the target "
                       "together (the warps live in the view's frame, so this stays honest).")
    color_jitter: float = Field(0.05, ge=0, le=0.5, description="Per-patch, per-channel gain "
                                "in [1-j, 1+j] applied to render, warps and target together "
                                "(an exposure / white-balance change of the whole capture); "
                                "alpha and weights untouched. 0 = off.")
    ckpt_every: int = Field(100, ge=1, description="Steps between resume checkpoints.")
    log_every: int = Field(10, ge=1, description="Steps between loss-curve lines.")
    eval_pairs: int = Field(8, ge=0, description="Held-out pairs (whole images) scored at the "
                            "end and shown on the contact sheet.")
