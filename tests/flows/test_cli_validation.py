"""Bad arguments end in one line naming the setting, scene or file (exit 2) before any flow
starts: no Prefect server, no traceback (issue: nothing lost, nothing stale)."""

from __future__ import annotations

import pytest

from flows import cli


@pytest.fixture
def no_evaluate_flow(monkeypatch):
    import flows.evaluate_engine as E

    monkeypatch.setattr(E, "evaluate_engine", lambda **kw: pytest.fail("the flow started"))


@pytest.mark.parametrize("args, needle", [
    (["--knob", "banana=1,2"], "unknown knob 'banana'"),
    (["--knob", "grid_r=banana"], "knob grid_r: expected a number or 'adaptive', got 'banana'"),
    (["--set", "banana=1"], "banana: Extra inputs are not permitted"),
    (["--set", "recon.max_iterations=abc"], "recon.max_iterations"),
    (["proc:nosuch"], "unknown evaluation scene 'proc:nosuch'"),
    (["real:kermit@nosuch"], "unknown real-scene family 'nosuch'"),
    (["--seeds", "-1"], "seeds must be >= 0"),
    (["--preset-set", "paper:seed=3"], "--preset-set names preset(s) ['paper']"),
    (["--preset", "fast", "--set", "preset=paper"], "--set preset=paper is not a field"),
])
def test_evaluate_quick_bad_arguments_are_one_line(no_evaluate_flow, tmp_path, capsys, args,
                                                   needle):
    rc = cli.main(["evaluate", "--quick", "--out", str(tmp_path / "ev"), *args])
    err = capsys.readouterr().err
    assert rc == 2 and needle in err and err.count("\n") == 1, err
    assert not (tmp_path / "ev").exists()


@pytest.mark.parametrize("args", [["--views", "1"], ["--views", "0"]])
def test_sample_scene_with_too_few_views_is_one_line(tmp_path, capsys, args):
    rc = cli.main(["sample-scene", str(tmp_path / "s"), *args])
    err = capsys.readouterr().err
    assert rc == 2 and "n_views must be >= 2" in err and str(tmp_path / "s") in err
    assert err.count("\n") == 1
