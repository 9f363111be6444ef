"""The whole pipeline's configuration: one typed object per stage, and named presets.

The same objects are the Prefect flow's parameters (``preset`` + ``overrides``), so what a
user can set on the command line, in a deployment or in the UI is exactly what is here.

Presets:

* ``paper``: the paper's numbers (METHOD.md) wherever they apply, sized per scene where the
  paper leaves it open (Gaussian budget, iterations, resolution, grid size).
* ``cpu``: the paper's selection and free-view numbers with a CPU-sized reconstruction
  (``ReconConfig.cpu()``: long side <= 512, compressed schedule, plateau stop).
* ``fast``: small numbers for tests, demos and CI (seconds per scene on a laptop CPU).
* ``auto`` (the command line's and the deployments' default): ``paper`` where CUDA is
  present, ``cpu`` otherwise; resolved once, in :func:`resolve_preset`, and the resolved name
  is what a config records.
"""

from __future__ import annotations

from typing import Any, Callable, Literal, get_args

from pydantic import BaseModel, ConfigDict, Field, model_validator

from .freeview import FreeViewConfig
from .ingest import IngestConfig
from .recon import ReconConfig
from .select import SelectConfig

PresetName = Literal["paper", "cpu", "fast"]

# The one preset table: preset name -> the stage configs that differ from the defaults.
PRESETS: dict[str, Callable[[], dict[str, BaseModel]]] = {
    "paper": lambda: {},
    "cpu": lambda: {"recon": ReconConfig.cpu()},
    "fast": lambda: {"recon": ReconConfig.fast(), "select": SelectConfig.fast(),
                     "freeview": FreeViewConfig.fast()},
}
assert set(PRESETS) == set(get_args(PresetName))

# What a user may ask for: a preset, or "auto" (resolved by resolve_preset).
PresetChoice = Literal["auto", "paper", "cpu", "fast"]
PRESET_CHOICES: tuple[str, ...] = get_args(PresetChoice)


def resolve_preset(name: str) -> str:
    """``auto`` -> ``paper`` where CUDA is present, ``cpu`` otherwise; other names unchanged."""
    if name != "auto":
        return name
    try:
        import torch

        return "paper" if torch.cuda.is_available() else "cpu"
    except Exception:  # noqa: BLE001 - no usable torch: the CPU preset
        return "cpu"


class PipelineConfig(BaseModel):
    """Configuration of ``generate-dataset`` for one run (applied to every scene)."""

    model_config = ConfigDict(extra="forbid")

    # PresetChoice, so that a deployment's parameter schema accepts "auto"; the validator
    # below resolves it, so a config always records the preset it really used
    preset: PresetChoice = Field("paper", description="preset the stage configs started from "
                                 "(auto is resolved: paper with CUDA, cpu without)")
    seed: int = Field(0, description="seed of every random choice; same seed, same store")
    recon_split: Literal["all", "ood", "every8"] = Field(
        "all", description="views that train the reconstruction: all, ood (first 70% in capture "
            "order) or every8 (every 8th held out)")
    ingest: IngestConfig = Field(default_factory=IngestConfig)
    recon: ReconConfig = Field(default_factory=ReconConfig)
    select: SelectConfig = Field(default_factory=SelectConfig)
    freeview: FreeViewConfig = Field(default_factory=FreeViewConfig)

    @model_validator(mode="before")
    @classmethod
    def _start_from_preset(cls, data: Any) -> Any:
        """A partial config starts from its preset: ``{"preset": "fast", "seed": 3}`` is the
        fast preset with seed 3 (fields not given take the preset's values, not the paper's).
        A complete config (a dump) is unchanged by this."""
        if not isinstance(data, dict):
            return data
        name = resolve_preset(data.get("preset", "paper"))
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}")
        base = {k: v.model_dump(mode="json") for k, v in PRESETS[name]().items()}
        given = {k: (v.model_dump(mode="json") if isinstance(v, BaseModel) else v)
                 for k, v in data.items()}
        return {**_deep_merge(base, given), "preset": name}

    @classmethod
    def from_preset(cls, preset: PresetChoice = "paper",
                    overrides: dict[str, Any] | None = None) -> "PipelineConfig":
        """The ``preset``, then nested ``overrides`` mirroring this model, e.g.
        ``{"select": {"nms": {"max_views": 200}}, "seed": 3}``. ``preset="auto"`` resolves
        with :func:`resolve_preset`."""
        return cls.model_validate({**(overrides or {}), "preset": preset})


def _deep_merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out
