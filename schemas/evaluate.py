"""Configuration of the ``evaluate-engine`` flow (``freescale_core.eval.sweep``; issue 16).

A sweep is a base pipeline config (a preset + overrides) and named knobs, each with values;
every (scene, point) is one run of ``generate-dataset`` into its own store. Points are the
base config, each knob value alone on top of it (one knob at a time), the presets asked for
(labelled points on the chart) and, with ``sizing``, the adaptive choice of each sizing knob
against half and double the value it chose per scene.
"""

from __future__ import annotations

from typing import Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field

from .pipeline import PresetName

KnobValue = Union[int, float, str]
SizingKnob = Literal["grid_r", "gaussians", "resolution", "candidates", "steps"]


class EvaluateConfig(BaseModel):
    """What ``freescale evaluate`` sweeps and how it scores."""

    model_config = ConfigDict(extra="forbid")

    preset: PresetName = Field("fast", description="preset of the base point (every knob "
                               "value is set on top of it)")
    overrides: dict[str, Any] = Field(
        default_factory=dict, description="nested PipelineConfig overrides of every point, "
        "e.g. {'recon': {'max_iterations': 150}}")
    recon_split: Literal["all", "ood", "every8"] = Field(
        "ood", description="recon_split of every point: ood gives held-out PSNR/SSIM (first "
        "70% train)")
    knobs: dict[str, list[KnobValue]] = Field(
        default_factory=dict, description="knob -> values, one knob at a time on the base "
        "(knob names: freescale_core.eval.knobs.KNOBS)")
    real_knobs: Literal["all", "recon"] = Field(
        "all", description="knobs on real scenes: all, or recon (only those that change the "
        "reconstruction, which held-out PSNR scores)")
    presets: list[PresetName] = Field(
        default_factory=list, description="presets run as labelled points (with preset_overrides)")
    preset_overrides: dict[str, dict[str, Any]] = Field(
        default_factory=dict, description="preset -> overrides of its labelled point "
        "(e.g. a time cap)")
    sizing: list[SizingKnob] = Field(
        default_factory=list, description="knobs whose adaptive choice is compared with half "
        "and double the chosen value per scene")
    true_psnr_db: float = Field(20.0, description="a free view is true when its PSNR against "
                                "the oracle is >= this (dB)")
    base_label: str = Field("base", description="label of the base point on the chart")
    warmup: bool = Field(
        True, description="before the first computed point, run the tiny scene once, untimed "
        "(kernel loading is then no point's cost)")
    seeds: list[int] = Field(
        default_factory=list, description="pipeline seeds: every point runs once per seed "
        "(empty: the preset's); charts and tables show means and spread")
    downstream: list[Literal["refine"]] = Field(
        default_factory=list, description="downstream gain per point: 'refine' = 3DGS refinement "
        "with vs without the free views")
    refine_steps: int = Field(150, ge=10, description="refinement steps of each arm (fixed, "
                              "same for both arms and every point)")
    refine_arm: str = Field("wiou", description="the arm with free views compared with the "
                            "real-views-only baseline (schemas/refine.py)")
    refine_seeds: list[int] = Field(default_factory=lambda: [0], description="refinement "
                                    "seeds; the gain is the mean over them")
    refine_overrides: dict[str, Any] = Field(
        default_factory=dict, description="RefineConfig overrides of the comparison, e.g. "
        "{'recon': {'max_long_side': 64}}")
    eval_long_side: int = Field(
        512, ge=16, description="held-out PSNR/SSIM of every point at this long side (px) per "
        "scene, whatever it trained at")
