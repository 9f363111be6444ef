"""`freescale refine`: the command line builds the RefineConfig the flow gets; the flow's
table formats one row per scene and refined arm."""

from __future__ import annotations

from flows import cli
from flows.refine_3dgs import format_table


def test_refine_command_builds_config(monkeypatch):
    got = {}
    import flows.refine_3dgs as F

    monkeypatch.setattr(F, "refine_3dgs", lambda **kw: got.update(kw))
    rc = cli.main(["refine", "STORE", "--scenes", "a", "b", "--arms", "baseline",
                   "wiou@reference", "random", "--seeds", "0", "2",
                   "--set", "recon.max_iterations=90", "--set", "per_step=3"])
    assert rc == 0
    cfg = got["config"]
    assert got["store"] == "STORE" and got["scenes"] == ["a", "b"]
    assert cfg.arm_names() == ["baseline", "wiou@reference", "random@reference"]
    assert cfg.seeds == [0, 2] and cfg.per_step == 3
    # a fixed budget: min = max, the rest of the refine budget kept
    assert cfg.recon.max_iterations == cfg.recon.min_iterations == 90
    assert cfg.recon.max_long_side == 128


def test_format_table_rows():
    s = {"scene": "x", "summary": {
        "baseline": {"seeds": [0, 1], "psnr": 20.0, "ssim": 0.5, "train_seconds": 10.0,
                     "n_added": 0},
        "wiou@paper": {"seeds": [0, 1], "psnr": 20.3, "ssim": 0.51, "train_seconds": 11.0,
                       "n_added": 10, "dpsnr": 0.3, "dpsnr_std": 0.1, "dssim": 0.01,
                       "overhead": 0.1}}}
    t = format_table([s]).splitlines()
    assert len(t) == 3 and "| x | wiou@paper | 2 | 10 | 20.00 | 20.30 | +0.30 (0.10)" in t[2]
    assert "+10%" in t[2]
