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
