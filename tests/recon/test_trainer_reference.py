"""The training loop's output at a fixed seed, pinned: a refactor of the trainer (the loop and
its plug-ins) must leave these bytes unchanged. The reference was written on the trainer
before it was split into plug-ins (commit 0d514ce); regenerate only for an intended change:

    PYTHONPATH=. python -m tests.recon.test_trainer_reference > tests/recon/trainer_reference.json
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

# learned background + its gate, SH schedule, plateau -> growth stop -> plateau -> anneal
REFERENCE = Path(__file__).with_name("trainer_reference.json")


def _run():
    import tempfile

    from freescale_core.recon.trainer import reconstruct
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene
    from schemas.recon import ReconConfig

    with tempfile.TemporaryDirectory() as tmp:
        d = write_sample_scene(Path(tmp) / "s", n_views=6, width=48, height=36, seed=0,
                               n_points=300)
        scene = load_scene(d)
        cfg = ReconConfig.fast().model_copy(update=dict(
            threads=1, torch_threads=1, max_long_side=48, max_iterations=240,
            min_iterations=20, plateau_window=20, plateau_ema_halflife=4.0, plateau_tol=0.3,
            anneal_fraction=0.1, densify_from=10, densify_every=10, densify_until=200,
            budget_min=100, cap_gaussians=600, sh_degree=2, sh_increase_every=30,
            train_eval_views=2, background_lr=0.05, background_lr_final=0.005,
            background_min_uncovered=0.001, background_gate_step=40, max_seconds=None))
        res = reconstruct(scene, cfg, seed=3)
    g = res.gaussians
    h = hashlib.sha256()
    for a in (g.means, g.log_scales, g.quats_wxyz, g.opacity_logits, g.sh):
        h.update(np.ascontiguousarray(a).tobytes())
    return {"params_sha256": h.hexdigest(), "background": [float(c) for c in res.background],
            "iterations": res.stats["iterations"], "n_gaussians": res.stats["n_gaussians"],
            "stop": res.stats["reasons"]["iterations"],
            "reasons": {k: res.stats["reasons"][k] for k in
                        ("background", "growth_stop", "sh_degree")},
            "loss_history": res.stats["loss"]["history"]}


def test_trainer_output_is_pinned():
    got = _run()
    assert got == json.loads(REFERENCE.read_text())


if __name__ == "__main__":
    print(json.dumps(_run(), indent=1))
