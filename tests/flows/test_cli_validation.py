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


def test_train_lvsm_on_a_truncated_chunk_is_one_line_naming_the_shard(tmp_path, monkeypatch,
                                                                     capsys):
    """Checked before the flow starts (was: a StoreError traceback logged by the task, and
    before the checksums a zstd RuntimeError naming no file)."""
    import flows.train_lvsm as T
    from tests.downstream.test_lvsm_from_shards import write_tiny_shards

    monkeypatch.setattr(T, "train_lvsm_flow", lambda **kw: pytest.fail("the flow started"))
    sh = write_tiny_shards(tmp_path / "sh", n_scenes=2)
    chunks = sorted(p for p in (sh / "shards").rglob("*") if p.is_file()
                    and "images" in p.parts and p.name != "zarr.json")
    chunks[0].write_bytes(chunks[0].read_bytes()[:5])
    shard = chunks[0].parents[len(chunks[0].relative_to(sh / "shards").parts) - 2]
    rc = cli.main(["train-lvsm", str(sh), "--out", str(tmp_path / "run"), "--steps", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and f"shard {shard} does not match its SHA-256" in err, err
    assert err.count("\n") == 1


def test_train_lvsm_resume_on_another_shards_folder_is_one_line(tmp_path, monkeypatch,
                                                               capsys):
    """Refused before the flow starts (was: the task's RunExistsError logged with two
    Prefect tracebacks before the error line); split.json untouched."""
    import json
    import shutil

    import flows.train_lvsm as T
    from tests.downstream.test_lvsm_from_shards import write_tiny_shards

    monkeypatch.setattr(T, "train_lvsm_flow", lambda **kw: pytest.fail("the flow started"))
    sh = write_tiny_shards(tmp_path / "sh", n_scenes=2)
    other = tmp_path / "other"
    shutil.copytree(sh, other)
    run = tmp_path / "run"
    (run / "ckpt").mkdir(parents=True)
    (run / "ckpt" / "last.pt").write_bytes(b"x")
    split = json.dumps({"shards": str(sh.absolute()), "manifest_sha256": ""})
    (run / "split.json").write_text(split)
    rc = cli.main(["train-lvsm", str(other), "--out", str(run), "--resume"])
    err = capsys.readouterr().err
    assert rc == 2 and f"shards {sh.absolute()} -> {other.absolute()}" in err, err
    assert err.count("\n") == 1 and (run / "split.json").read_text() == split


def test_a_deleted_version_folder_is_not_complete(tmp_path):
    """CURRENT names a version folder deleted by hand: the scene is not 'already complete'
    (it runs again) instead of the flow failing and the CLI suggesting the same resume."""
    import logging

    from flows.generate_dataset import _published
    from freescale_core.store.store import Store

    st = Store(tmp_path / "store")
    st.update_status("a", status="ok")
    (st.scene_dir("a") / "CURRENT").write_text("v0001\n")
    assert _published(st, "a", logging.getLogger("t")) is False
    (st.scene_dir("a") / "v0001").mkdir()
    assert _published(st, "a", logging.getLogger("t")) is True
