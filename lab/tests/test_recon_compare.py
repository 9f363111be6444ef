"""``python -m lab.recon_compare``: the benchmark's ``--compare`` with the frozen legacy arms
(``lab/arms``) and the old trainer's switches as plug-ins (``lab/legacy.py``)."""

from __future__ import annotations

import json

import pytest

from lab import legacy, recon_compare


def test_legacy_arms_and_switches():
    (old, old_sw), (new, new_sw) = recon_compare.arm("old"), recon_compare.arm("new")
    assert old.bounds_every == 0 and old.coarse_to_fine == () and new.bounds_every > 0
    # the trainer as issue 17 found it: switches of lab/legacy.py, not ReconConfig fields
    assert old_sw == {"mcmc_scale_invariant": False, "raster_exact_tiles": False,
                      "ssim_impl": "torch"} and new_sw == {}
    kw = recon_compare.arm.plugins(old, old_sw)
    assert sorted(kw) == ["photometric", "rasterizer", "strategy"]
    assert isinstance(kw["strategy"], legacy.WorldUnitsMCMC)
    assert recon_compare.arm.plugins(old, old_sw)["strategy"] is not kw["strategy"]  # per run
    assert recon_compare.arm("pre55")[1] == {}  # its dump holds today's values: no plug-in
    cfg, sw = recon_compare.arm("new,bounds_every=7,ssim_impl=torch")
    assert cfg.model_dump() == new.model_copy(update={"bounds_every": 7}).model_dump()
    assert sw == {"ssim_impl": "torch"}
    with pytest.raises(SystemExit, match="ssim_impl"):
        recon_compare.arm("new,ssim_impl=numpy")
    # the stop-55 arms: the preset is the pre-55 preset plus H's five fields, nothing else
    h = ("pre55,background_lr=0.01,background_lr_final=0.0001,background_min_uncovered=0.005,"
         "sh_views_per_coeff=2,sh_cap_min_gain_std=0.05")
    assert recon_compare.arm_config(h).model_dump() == new.model_dump()
    pre = recon_compare.arm_config("pre55")
    assert pre.background_lr is None and pre.sh_views_per_coeff is None
    with pytest.raises(SystemExit, match="no frozen config"):
        recon_compare.legacy_arm("nope")


def test_compare_runs_a_legacy_arm_through_the_plugins(tmp_path, monkeypatch, capsys):
    """A legacy arm runs through the benchmark's ``run(..., plugins=)`` with its switches'
    plug-ins, and its row records the switches under their old keys."""
    from benchmarks import recon
    from freescale_core.scene.sample import write_sample_scene

    seen = []
    real = recon.run

    def spy(*args, **kw):
        seen.append(sorted(args[10] or {}))  # the plugins argument
        return real(*args, **kw)

    monkeypatch.setattr(recon, "run", spy)
    d = write_sample_scene(tmp_path / "s", n_views=6, width=48, height=36, seed=0, n_points=300)
    out = tmp_path / "rows.jsonl"
    assert recon_compare.main([str(d), "--compare", "old-fast", "new-fast",
                               "--max-iterations", "8", "--max-long-side", "48", "--threads",
                               "1", "--eval-every", "4", "--out", str(out)]) == 0
    rows = {r["arm"]: r for r in map(json.loads, out.read_text().splitlines())}
    assert seen == [["photometric", "rasterizer", "strategy"], []]
    assert rows["old-fast"]["config"]["ssim_impl"] == "torch"
    assert rows["old-fast"]["config"]["mcmc_scale_invariant"] is False
    assert "ssim_impl" not in rows["new-fast"]["config"]
