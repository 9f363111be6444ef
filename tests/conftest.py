"""Shared fixtures: the real scenes in ../shared/datasets (skipped when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("FREESCALE_DATASETS", REPO.parent / "shared" / "datasets"))
REAL_SCENES = ["kermit", "buddha", "llff_fern", "strecha_fountain-P11", "dtu_scan24"]


def real_scene_dir(name: str) -> Path:
    """Path of a shared real scene, or skip the test with the reason."""
    p = DATASETS / name
    if not (p / "sparse" / "0").is_dir():
        pytest.skip(f"shared dataset {name!r} not found under {DATASETS} (set FREESCALE_DATASETS)")
    return p


@pytest.fixture(params=REAL_SCENES)
def real_scene(request) -> Path:
    return real_scene_dir(request.param)


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    if not DATASETS.is_dir():
        pytest.skip(f"shared datasets folder not found: {DATASETS}")
    return DATASETS
