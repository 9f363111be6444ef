"""The whole pipeline's configuration: one typed object per stage, and named presets.

The same objects are the Prefect flow's parameters (``preset`` + ``overrides``), so what a
user can set on the command line, in a deployment or in the UI is exactly what is here.

Presets:

* ``paper``: the paper's numbers (METHOD.md) wherever they apply, sized per scene where the
  paper leaves it open (Gaussian budget, iterations, resolution, grid size).
* ``cpu``: the paper's selection and free-view numbers with a CPU-sized reconstruction
  (``ReconConfig.cpu()``: long side <= 512, compressed schedule, plateau stop).
* ``fast``: small numbers for tests, demos and CI (seconds per scene on a laptop CPU).
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .freeview import FreeViewConfig
from .ingest import IngestConfig
from .recon import ReconConfig
from .select import SelectConfig

PresetName = Literal["paper", "cpu", "fast"]


class PipelineConfig(BaseModel):
    """Configuration of ``generate-dataset`` for one run (applied to every scene)."""

    model_config = ConfigDict(extra="forbid")

    preset: PresetName = Field("paper", description="preset the stage configs started from")
    seed: int = Field(0, description="seed of every random choice; same seed, same store")
    recon_split: Literal["all", "ood", "every8"] = Field(
        "all", description="which captured views train the reconstruction: all (data "
        "generation), ood (first 70% in capture order; evaluation protocol of the paper) "
        "or every8 (every 8th view held out)")
    ingest: IngestConfig = Field(default_factory=IngestConfig)
    recon: ReconConfig = Field(default_factory=ReconConfig)
    select: SelectConfig = Field(default_factory=SelectConfig)
    freeview: FreeViewConfig = Field(default_factory=FreeViewConfig)

    @classmethod
    def from_preset(cls, preset: PresetName = "paper",
                    overrides: dict[str, Any] | None = None) -> "PipelineConfig":
        """Build a config from a preset, then apply nested ``overrides``.

        ``overrides`` is a nested dict mirroring this model, e.g.
        ``{"select": {"nms": {"max_views": 200}}, "seed": 3}``.
        """
        if preset == "paper":
            base = cls(preset="paper")
        elif preset == "cpu":
            base = cls(preset="cpu", recon=ReconConfig.cpu())
        elif preset == "fast":
            base = cls(preset="fast", recon=ReconConfig.fast(), select=SelectConfig.fast(),
                       freeview=FreeViewConfig.fast())
        else:
            raise ValueError(f"unknown preset {preset!r}; expected 'paper', 'cpu' or 'fast'")
        if overrides:
            merged = _deep_merge(base.model_dump(mode="json"), overrides)
            base = cls.model_validate(merged)
        return base


def _deep_merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out
