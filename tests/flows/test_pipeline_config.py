"""Presets and overrides of the pipeline config (the flow's parameters)."""

import pytest
from pydantic import ValidationError

from schemas.pipeline import PipelineConfig


def test_presets_differ_where_documented():
    paper, cpu, fast = (PipelineConfig.from_preset(n) for n in ("paper", "cpu", "fast"))
    assert paper.select.grid.resolution == 128 and paper.select.nms.max_views == 500
    assert paper.recon.max_iterations == 30_000
    assert cpu.select == paper.select and cpu.recon.max_iterations < paper.recon.max_iterations
    assert fast.select.grid.resolution < paper.select.grid.resolution


def test_overrides_nest_and_validate():
    c = PipelineConfig.from_preset("fast", {"select": {"nms": {"max_views": 7}}, "seed": 3})
    assert c.select.nms.max_views == 7 and c.seed == 3 and c.preset == "fast"
    with pytest.raises(ValidationError):
        PipelineConfig.from_preset("fast", {"select": {"nms": {"no_such_field": 1}}})
    with pytest.raises(ValueError):
        PipelineConfig.from_preset("huge")


def test_one_preset_table_and_partial_configs_start_from_their_preset():
    """A deployment's ``config={"preset": "fast", ...}`` is the fast preset plus the given
    fields (not the paper defaults plus them); a complete dump round-trips unchanged."""
    from typing import get_args

    from schemas.pipeline import PRESETS, PresetName

    assert set(PRESETS) == set(get_args(PresetName))
    c = PipelineConfig.model_validate({"preset": "fast", "seed": 3})
    assert c == PipelineConfig.from_preset("fast", {"seed": 3})
    assert c.select.grid.resolution == PipelineConfig.from_preset("fast").select.grid.resolution
    for name in PRESETS:
        full = PipelineConfig.from_preset(name)
        assert PipelineConfig.model_validate(full.model_dump(mode="json")) == full
    with pytest.raises(ValidationError):
        PipelineConfig.model_validate({"preset": "huge"})
