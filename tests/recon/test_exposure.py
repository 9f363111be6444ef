"""The SH cap where the training views disagree in exposure (``sh_cap_min_gain_std``): the
cap applies only when the views' log colour gains, measured on the sparse points, spread.
(Per-view exposure compensation, tried in stops 29 and 36, is no longer a trainer option:
lab/results/2026-12-03_stop29/, lab/results/2026-12-04_stop36/.)"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from freescale_core.recon.trainer import reconstruct
from schemas.recon import ReconConfig


@pytest.fixture(scope="module")
def cast_scene(tmp_path_factory):
    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("expo")
    d = write_sample_scene(root / "s", n_views=16, width=64, height=48)
    return load_scene(d, cache_dir=root / "cache")


def _fit(scene, upd, train):
    cfg = ReconConfig.fast().model_copy(update=dict(max_iterations=40, threads=1, **upd))
    r = reconstruct(scene, cfg, seed=3, train_idx=train)
    g = r.gaussians
    h = hashlib.sha256(b"".join(np.ascontiguousarray(a).tobytes() for a in (
        g.means, g.log_scales, g.quats_wxyz, g.opacity_logits, g.sh))).hexdigest()
    return r.stats, h


def _paint_gains(monkeypatch, train, seed: int = 0):
    """From now on the training photos load with one gain in [0.6, 1.4] per view."""
    from freescale_core.scene.scene import Scene

    rng = np.random.default_rng(seed)
    gains = {int(i): rng.uniform(0.6, 1.4) for i in train}
    orig = Scene.load_image

    def cast(self, i):
        return np.clip(np.round(orig(self, i) * gains.get(int(i), 1.0)), 0, 255).astype(np.uint8)

    monkeypatch.setattr(Scene, "load_image", cast)


# --- sh_cap_min_gain_std: the SH view-count cap only where the views' gains spread -------------

def test_sh_cap_only_where_the_views_disagree(cast_scene, monkeypatch):
    """14 training views: the cap (2 views per coefficient) gives degree 1. With the rule the
    trainer is bit-identical to the uncapped one on photos that agree with their points, and
    to the always-capped one once the same photos carry per-view gains."""
    train = cast_scene.split("every8")[0]
    sh = dict(sh_degree=3, sh_increase_every=5)
    rule = dict(sh, sh_views_per_coeff=2.0, sh_cap_min_gain_std=0.05)
    st_free, h_free = _fit(cast_scene, dict(sh, sh_views_per_coeff=None), train)
    st_cap, h_cap = _fit(cast_scene, dict(sh, sh_views_per_coeff=2.0), train)
    assert (st_free["sh_degree"], st_cap["sh_degree"]) == (3, 1) and h_free != h_cap
    st_rule, h_rule = _fit(cast_scene, rule, train)
    assert h_rule == h_free and st_rule["sh_degree"] == 3
    assert st_rule["exposure_gain_std"] < 0.05
    assert "cap off" in st_rule["reasons"]["sh_degree"]

    _paint_gains(monkeypatch, train)
    _, h_cap_cast = _fit(cast_scene, dict(sh, sh_views_per_coeff=2.0), train)
    st_rc, h_rc = _fit(cast_scene, rule, train)
    assert h_rc == h_cap_cast and st_rc["sh_degree"] == 1
    assert st_rc["exposure_gain_std"] > 0.1 and "> 0.05" in st_rc["reasons"]["sh_degree"]
