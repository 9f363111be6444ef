"""The sample scene's exact renderer, the source of truth at any pose."""

from __future__ import annotations

from pathlib import Path


def ground_truth_oracle(scene_path: str | Path | None):
    """The sample scene's exact renderer when the scene has one (``scene.json``), else None."""
    if scene_path is None or not (Path(scene_path) / "scene.json").is_file():
        return None
    from freescale_core.scene.sample import SampleWorld

    return SampleWorld.load(scene_path)
