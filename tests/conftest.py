"""Shared fixtures: the real scenes in ../shared/datasets (skipped when absent)."""

from __future__ import annotations

import copy

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


# --------------------------------------------------------------------------- a tiny store
# The fast preset made smaller still (as tests/flows/test_flow.py uses): seconds per scene.
TINY_OVERRIDES = {"recon": {"max_iterations": 80, "min_iterations": 40, "densify_from": 20,
                            "densify_until": 60, "densify_every": 20, "max_long_side": 64,
                            "cap_gaussians": 2000},
                  "freeview": {"final": {"target": 10}}}


def build_store(store: Path, scenes: dict[str, Path], overrides: dict | None = None) -> Path:
    """Run every stage of generate-dataset on ``scenes`` ({scene_id: folder}) into ``store``
    by calling the tasks' functions directly (no Prefect server): the real publish path."""
    from schemas.pipeline import PipelineConfig
    from tasks import scene_tasks as T
    from freescale_core.store.store import config_hash

    cfg = PipelineConfig.from_preset("fast", overrides or TINY_OVERRIDES)
    st = str(store)
    for sid, p in scenes.items():
        i = T.ingest.fn(st, sid, str(p), cfg)
        r = T.reconstruct.fn(st, i, str(p), cfg)
        s = T.select.fn(st, i, r, cfg)
        f = T.freeviews.fn(st, i, r, s, str(p), cfg)
        T.publish.fn(st, i, r, s, f, cfg, config_hash(cfg), str(p))
    return store


@pytest.fixture(scope="session")
def dataset_store(tmp_path_factory) -> Path:
    """A published store with the sample scene (30 views, 96x72) and, when the shared
    datasets are present, kermit (undistorted images, free views of a few different sizes)."""
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("dataset_store")
    write_sample_scene(root / "scenes" / "sample_a", n_views=30, width=96, height=72, seed=0)
    build_store(root / "store", {"sample_a": root / "scenes" / "sample_a"})
    if (DATASETS / "kermit" / "sparse" / "0").is_dir():
        # 150 steps, not the tiny 80: at 80 (train PSNR ~16 dB at 64 px) the trust filter's
        # verdicts sit on its thresholds, and a dependency update (2026-12-02) left 2 free
        # views of one size, so the mixed-size test had nothing to test; 150 steps give 7
        # views in 3 sizes
        kermit = copy.deepcopy(TINY_OVERRIDES)
        kermit["recon"].update(max_iterations=150, min_iterations=75, densify_until=110)
        build_store(root / "store", {"kermit": DATASETS / "kermit"}, kermit)
    return root / "store"
