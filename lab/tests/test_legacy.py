"""The old trainer's switches as plug-ins (``lab/legacy.py``): the ``old-fast`` arm run through
them gives the bytes the trainer gave when the switches were ``ReconConfig`` fields."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from lab import legacy

ARMS = Path(__file__).resolve().parents[1] / "arms"
# sha256 of the Gaussians of _run() with the old-fast arm, on commit 6091708 (the switches
# still fields of ReconConfig, set by the dump)
OLD_FAST_SHA = "be27f0c583297cf73d44c80abcc93d2febbb862a4942a588d352ed176e8ba91c"


def _run(with_plugins: bool) -> tuple[int, str]:
    import tempfile

    from freescale_core.recon.trainer import reconstruct
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene
    from schemas.recon import ReconConfig

    fields, switches = legacy.split(json.loads((ARMS / "old-fast.json").read_text())["recon"])
    cfg = ReconConfig.model_validate({**fields, **dict(
        threads=1, torch_threads=1, max_long_side=48, max_iterations=60, min_iterations=60,
        densify_from=10, densify_every=10, densify_until=50, budget_min=100, cap_gaussians=600,
        train_eval_views=2)})
    kw = legacy.plugins(cfg, switches) if with_plugins else {}
    with tempfile.TemporaryDirectory() as tmp:
        d = write_sample_scene(Path(tmp) / "s", n_views=6, width=48, height=36, seed=0,
                               n_points=300)
        g = reconstruct(load_scene(d), cfg, seed=3, **kw).gaussians
    h = hashlib.sha256()
    for k in ("means", "log_scales", "quats_wxyz", "opacity_logits", "sh"):
        h.update(np.ascontiguousarray(getattr(g, k)).tobytes())
    return len(g), h.hexdigest()


def test_old_fast_arm_through_the_plugins_is_the_old_trainer():
    assert _run(True) == (600, OLD_FAST_SHA)
    assert _run(False)[1] != OLD_FAST_SHA  # today's trainer differs: the plug-ins do the work


def test_split_keeps_only_switches_that_differ_from_today():
    fields, sw = legacy.split({"bounds_every": 0, "ssim_impl": "fused",
                               "mcmc_scale_invariant": False})
    assert fields == {"bounds_every": 0} and sw == {"mcmc_scale_invariant": False}
    assert legacy.plugins(None, {}) == {}
    with pytest.raises(ValueError, match="raster_exact_tiles"):
        legacy.split({"raster_exact_tiles": "no"})
