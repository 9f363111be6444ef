"""`freescale refine`: the command line builds the RefineConfig the flow gets; the flow's
table formats one row per scene and refined arm."""

from __future__ import annotations

import pytest

from flows import cli
from flows.cli import refine as refine_cli
from flows.refine_3dgs import format_table


def test_refine_command_builds_config(monkeypatch):
    got = {}
    import flows.refine_3dgs as F

    monkeypatch.setattr(F, "refine_3dgs", lambda **kw: got.update(kw))
    monkeypatch.setattr(refine_cli, "_refine_preflight", lambda *a: None)
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


@pytest.mark.parametrize("args, needle", [
    (["--arms", "banana"], "unknown arm 'banana'"),
    (["--set", "banana=1"], "banana: Extra inputs are not permitted"),
    (["--set", "recon.max_iterations=abc"], "recon.max_iterations"),
    (["--seeds", "-1"], "seeds must be >= 0"),
    (["--seeds", "1", "1"], "without repeats"),
    (["--scenes", "nosuch"], "['nosuch'] are not in the store"),
    ([], "has no held-out views"),
])
def test_refine_bad_arguments_are_one_line_before_the_flow(dataset_store, monkeypatch, capsys,
                                                           args, needle):
    import flows.refine_3dgs as F

    monkeypatch.setattr(F, "refine_3dgs", lambda **kw: pytest.fail("the flow started"))
    rc = cli.main(["refine", str(dataset_store), *args])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and err.count("\n") == 1, err


def test_refine_without_a_store_is_one_line(tmp_path, monkeypatch, capsys):
    import flows.refine_3dgs as F

    monkeypatch.setattr(F, "refine_3dgs", lambda **kw: pytest.fail("the flow started"))
    rc = cli.main(["refine", str(tmp_path / "nostore")])
    err = capsys.readouterr().err
    assert rc == 2 and f"no store at {tmp_path / 'nostore'}" in err and err.count("\n") == 1
