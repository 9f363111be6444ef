"""Configuration of the LVSM downstream task (METHOD.md "Downstream uses": LVSM training).

Two configs:

* ``LVSMModelConfig``: the decoder-only LVSM transformer
  (``freescale_core.downstream.lvsm.model``). Named presets: ``"cpu"`` (the default: d=128,
  4 layers, 4 heads, 64 px, patch 8; trains on a laptop CPU) and ``"paper"`` (LVSM's size:
  d=768, 24 layers, 12 heads of dim 64, 256 px, patch 8).
* ``LVSMSamplerConfig``: which views form one training example
  (``freescale_core.downstream.lvsm.sampler``). Defaults are the paper's: 4 inputs -> 2 targets,
  frame distance [15, 40] annealed from [10, 20], view-graph batches with probability 0.5,
  free-view targets weighted 0.3.
"""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


class LVSMModelConfig(BaseModel):
    """Decoder-only LVSM (Jin et al., ICLR 2025) sized by the fields below."""

    model_config = ConfigDict(extra="forbid")

    d_model: int = Field(128, ge=1, description="Token width d (cpu: 128, paper: 768).")
    n_layers: int = Field(4, ge=1, description="Transformer blocks (cpu: 4, paper: 24).")
    n_heads: int = Field(4, ge=1, description="Attention heads; d_model / n_heads is the head dim.")
    image_size: int = Field(
        64, ge=1, description="Training image side in pixels (cpu: 64, paper: 256). The model has "
        "no positional table, so any H, W divisible by patch_size also runs.")
    patch_size: int = Field(8, ge=1, description="Square patch side p in pixels (both: 8).")
    mlp_ratio: float = Field(4.0, gt=0, description="MLP hidden width / d_model (4x).")
    qk_norm: Literal["layernorm", "rmsnorm"] = Field(
        "layernorm", description="Per-head normalisation of q and k before attention.")
    attention: Literal["sdpa", "reference"] = Field(
        "sdpa", description="'sdpa' = torch scaled_dot_product_attention; 'reference' = the "
        "explicit softmax(QK^T/sqrt(d))V (slow; for tests).")
    normalize_poses: bool = Field(
        True, description="Recentre/rotate/scale every sample's cameras on its input cameras "
        "(normalize_poses) so predictions ignore the scene's similarity frame.")
    init_std: float = Field(0.02, gt=0, description="Std of the normal init of Linear weights.")
    norm_eps: float = Field(1e-5, gt=0, description="Epsilon of every LayerNorm / RMSNorm.")

    PRESETS: ClassVar[dict[str, dict[str, Any]]] = {
        "cpu": dict(d_model=128, n_layers=4, n_heads=4, image_size=64, patch_size=8),
        "paper": dict(d_model=768, n_layers=24, n_heads=12, image_size=256, patch_size=8),
    }

    @classmethod
    def preset(cls, name: Literal["cpu", "paper"], **overrides: Any) -> LVSMModelConfig:
        """Config of a named preset ("cpu" | "paper"), with field overrides applied."""
        if name not in cls.PRESETS:
            raise ValueError(f"unknown LVSM preset {name!r}; choose one of {sorted(cls.PRESETS)}")
        return cls(**{**cls.PRESETS[name], **overrides})

    @property
    def head_dim(self) -> int:
        """Per-head width d_model / n_heads."""
        return self.d_model // self.n_heads

    @model_validator(mode="after")
    def _check(self) -> LVSMModelConfig:
        if self.d_model % self.n_heads:
            raise ValueError(f"d_model={self.d_model} is not divisible by n_heads={self.n_heads}")
        if self.image_size % self.patch_size:
            raise ValueError(f"image_size={self.image_size} is not divisible by "
                             f"patch_size={self.patch_size}")
        return self


class LVSMSamplerConfig(BaseModel):
    """Which views form one LVSM training example (METHOD.md "LVSM training")."""

    model_config = ConfigDict(extra="forbid")

    n_input: int = Field(4, ge=2, description="Input views per example (paper: 4).")
    n_target: int = Field(2, ge=1, description="Target views per example (paper: 2).")
    frame_dist: tuple[int, int] = Field(
        (15, 40), description="Frame branch: span (first to last view of the window, in captured "
        "frames) after warm-up, at reference_length frames (paper: [15, 40]).")
    warmup_frame_dist: tuple[int, int] = Field(
        (10, 20), description="Frame branch: span at step 0; annealed linearly to frame_dist "
        "over warmup_steps (paper: [10, 20]).")
    reference_length: int | None = Field(
        300, ge=1, description="Capture length (captured views) at which the spans hold as given; "
        "a capture of n views scales them by n / reference_length (DL3DV captures hold ~200-400 "
        "frames; 300 assumed). None = no scaling.")
    warmup_steps: int = Field(
        3_000, ge=0, description="Curriculum length in training steps (paper: the 3k lr warm-up).")
    graph_prob: float = Field(
        0.5, ge=0, le=1, description="Probability an example comes from the view graph (paper: "
        "0.5); only when use_free_views.")
    graph_sharpness: float = Field(
        2.0, ge=0, description="Graph branch: edges are drawn with probability proportional to "
        "wiou^t in warm-up and (1 - wiou)^t after; t = this (0 = uniform).")
    novel_target_weight: float = Field(
        0.3, ge=0, description="Loss weight of a free-view (generated) target; captured = 1.")
    target_mode: Literal["between", "extrapolate"] = Field(
        "between", description="'between' (LVSM): targets strictly between the first and last "
        "input frame; 'extrapolate': inputs and targets drawn from the window together, so "
        "targets may fall outside the inputs along the path.")
    use_free_views: bool = Field(
        True, description="False: frame branch only, free views never drawn (arms A / A').")
    random_free: bool = Field(
        False, description="Arm D: the graph branch draws its views uniformly at random from the "
        "scene instead of walking the view graph.")
    swap_hops: int = Field(
        2, ge=1, description="A graph example made only of free views swaps one input for a "
        "captured view within this many hops.")

    @property
    def n_views(self) -> int:
        """Views per example, n_input + n_target."""
        return self.n_input + self.n_target

    @model_validator(mode="after")
    def _check(self) -> LVSMSamplerConfig:
        for name in ("frame_dist", "warmup_frame_dist"):
            lo, hi = getattr(self, name)
            if not 1 <= lo <= hi:
                raise ValueError(f"{name}={(lo, hi)} must satisfy 1 <= lo <= hi")
        return self


class TrainLVSMConfig(BaseModel):
    """LVSM training run (``freescale_core.downstream.lvsm.train.train_lvsm``).

    AdamW; the learning rate rises linearly to ``lr`` over ``warmup_steps`` then follows a
    cosine to ``lr * min_lr_ratio`` at ``steps``. The paper: lr 4e-4, 3k warm-up, grad clip 1,
    bf16 on GPU.
    """

    model_config = ConfigDict(extra="forbid")

    steps: int = Field(1000, ge=1, description="Optimiser steps.")
    batch_size: int = Field(8, ge=1, description="Examples per step.")
    lr: float = Field(4e-4, gt=0, description="Peak learning rate (paper: 4e-4).")
    warmup_steps: int = Field(100, ge=0, description="Linear lr warm-up (paper: 3000).")
    min_lr_ratio: float = Field(0.0, ge=0, le=1, description="Final lr / peak lr (cosine end).")
    weight_decay: float = Field(0.05, ge=0, description="AdamW decoupled weight decay.")
    betas: tuple[float, float] = Field((0.9, 0.95), description="AdamW betas (paper: 0.9, 0.95).")
    grad_clip: float = Field(1.0, gt=0, description="Max global grad norm.")
    confidence_weight: bool = Field(
        False, description="Weight each target pixel's loss by its view's confidence (the "
        "fixer's, 1 for photos).")
    bf16: bool = Field(False, description="bf16 autocast (ignored on CPU: always off there).")
    device: str = Field("cpu", description="torch device.")
    log_every: int = Field(10, ge=1, description="Steps between log lines.")
    eval_every: int = Field(100, ge=1, description="Steps between held-out evaluations.")
    eval_samples: int = Field(16, ge=1, description="Fixed held-out examples per evaluation.")
    ckpt_every: int = Field(100, ge=1, description="Steps between checkpoints.")
    model_preset: Literal["cpu", "paper"] = Field("cpu", description="LVSMModelConfig preset.")
    model_overrides: dict[str, Any] = Field(default_factory=dict,
                                            description="LVSMModelConfig field overrides.")
    sampler: LVSMSamplerConfig = Field(default_factory=LVSMSamplerConfig)

    def model(self) -> LVSMModelConfig:
        """The model config: the preset with ``model_overrides`` applied."""
        return LVSMModelConfig.preset(self.model_preset, **self.model_overrides)


class TrainLVSMShardsConfig(BaseModel):
    """The ``train-lvsm`` flow: an LVSM trained from packed shards (``freescale shards pack``).

    Held-out data: the scenes ``heldout_scenes`` (default: the last ``n_heldout_scenes`` by
    scene id) and, with ``heldout_tail``, the last frames of each training scene's capture.
    """

    model_config = ConfigDict(extra="forbid")

    train: TrainLVSMConfig = Field(
        default_factory=TrainLVSMConfig,
        description="The training run: steps, batch, lr, checkpoints, model preset, sampler.")
    scenes: list[str] | None = Field(
        None, description="Scene ids of the shards to use (None: every scene in the manifest).")
    heldout_scenes: list[str] | None = Field(
        None, description="Held-out scene ids, never trained on (None: the last n_heldout_scenes "
        "by scene id).")
    n_heldout_scenes: int = Field(
        1, ge=0, description="Held-out scenes when heldout_scenes is None (the last by id; none "
        "when fewer than 2 scenes).")
    heldout_tail: float | None = Field(
        None, ge=0, lt=1, description="Share of each training capture held out as views (its last "
        "frames); None: 0.3 if no scene is held out, else 0.")
    min_heldout_frames: int = Field(
        6, ge=2, description="A held-out tail shorter than this many captured frames is skipped.")


class LVSMEvalConfig(BaseModel):
    """Evaluation regimes on held-out scenes (``freescale_core.eval.lvsm_eval``).

    Frame counts are positions in the capture order; inputs are spread evenly over their
    window (both ends included).
    """

    model_config = ConfigDict(extra="forbid")

    n_input: int = Field(4, ge=1, description="Input views per example.")
    n_per_scene: int = Field(4, ge=1, description="Examples per regime per scene.")
    small_span: int = Field(6, ge=2, description="small: inputs span this many frames; the "
                            "target is a frame strictly between them (not an input).")
    large_span: int = Field(6, ge=1, description="large: inputs span this many frames.")
    extrap_frames: tuple[int, int] = Field(
        (4, 8), description="large: the target lies this many frames (drawn in the range) "
        "after the last input or before the first, along the path.")
    offpath_span: int = Field(6, ge=1, description="off-path: inputs span this many frames "
                              "centred on the capture frame nearest the target.")
    offpath_min_distance: float = Field(0.5, gt=0, description="off-path: the target camera "
                                        "is at least this far (m) from every capture camera.")
    seed: int = Field(2024, description="Draws of windows, targets and off-path poses.")

    @model_validator(mode="after")
    def _check(self) -> LVSMEvalConfig:
        if self.small_span < self.n_input:
            raise ValueError(f"small_span={self.small_span} leaves no frame between "
                             f"{self.n_input} inputs")
        lo, hi = self.extrap_frames
        if not 1 <= lo <= hi:
            raise ValueError(f"extrap_frames={(lo, hi)} must satisfy 1 <= lo <= hi")
        return self
