"""Issue 12: bad input, crashes and real-tool captures: every case a correct result or a clear
error, nothing lost. Quick CLI / flow cases; the full set is ``benchmarks/faults.py``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
# Prefect binds its log handlers to sys.stderr when first imported: import it here, not
# inside a test whose stderr is a capsys buffer that is closed afterwards.
import prefect  # noqa: E402,F401
from prefect.logging.configuration import setup_logging  # noqa: E402

setup_logging()

REPO = Path(__file__).resolve().parents[2]


def _failed_store(root: Path) -> Path:
    from freescale_core.store.store import Store

    st = Store(root)
    st.update_status("bad_scene", status="failed", stage="ingest",
                     error="[ingest] scene 'bad_scene': image cannot be decoded [/data/x/[b]/img.png]",
                     error_type="CorruptImageError")
    st.update_status("good", status="ok", counts={"n_free_views": 3})
    return root


def test_cli_prints_errors_ending_in_a_bracketed_path(tmp_path, capsys):
    """An error ends in ``[<path>]``: rich must print it as text, not parse it as a tag."""
    from flows.cli import main

    store = _failed_store(tmp_path / "store")
    assert main(["scenes", "ls", str(store)]) == 0
    out = capsys.readouterr().out
    assert "bad_scene" in out and "/data/x/" in out and "img.png" in out
    assert "[b]" in out  # shown literally, not eaten as markup


def test_print_manifest_survives_markup_in_every_cell(tmp_path, capsys):
    from flows.cli.scenes import _print_manifest
    from freescale_core.store.store import Store

    st = Store(tmp_path / "[s]")
    st.update_status("[x]", status="failed", error="[/bold] [red]x[/red] [/a/b]")
    _print_manifest(st)
    out = capsys.readouterr().out
    assert "[/bold]" in out and "[/a/b]" in out


# --------------------------------------------------------------------------- flow cases
from tests.flows.test_flow import SAMPLE_KW, TINY, TINY_SET  # noqa: E402  (one tiny config)

TINY_SET_PAIRS = TINY_SET[1::2]


@pytest.fixture(scope="module")
def harness():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        from prefect.settings import PREFECT_API_URL

        yield PREFECT_API_URL.value()


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("rel_scenes")
    write_sample_scene(root / "sample", seed=0, **SAMPLE_KW)
    return root / "sample"


def _cfg(**extra):
    from schemas.pipeline import PipelineConfig

    over = json.loads(json.dumps(TINY))
    for k, v in extra.items():
        d = over
        parts = k.split(".")
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = v
    return PipelineConfig.from_preset("fast", over)


def _run(scenes, store, **kw):
    from flows.generate_dataset import generate_dataset

    cfg = kw.pop("config", None) or _cfg()
    return generate_dataset(scenes=[str(s) for s in scenes], store=str(store), config=cfg,
                            return_state=True, **kw)


def test_zero_free_views_says_why_and_writes_empty_arrays(harness, sample, tmp_path):
    import contextlib
    import io

    from flows.cli.scenes import _print_manifest
    from freescale_core.store.store import Store

    store = tmp_path / "store"
    state = _run([sample], store, config=_cfg(**{"select.nms.max_views": 0}))
    assert state.is_completed(), state.message
    assert "0 free views" in state.message and "0 selected by NMS" in state.message
    st = Store(store)
    row = st.manifest().to_pylist()[0]
    assert row["status"] == "ok" and row["n_free_views"] == 0
    assert row["empty_reason"].startswith("0 free views: ")
    assert "budget" in row["empty_reason"]
    rgb = st.arrays("sample")["freeviews/rgb"]  # the README's reader works
    assert rgb.shape[0] == 0 and rgb.ndim == 4 and rgb.shape[3] == 3
    assert st.arrays("sample")["freeviews/view_id"].shape == (0,)
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        _print_manifest(st)
    assert "warning: sample: 0 free views" in err.getvalue()


def test_scene_ids_all_clashing_folders_renamed_on_the_original_names():
    from flows.generate_dataset import scene_ids_for

    paths = [Path(f"/d/{p}/colmap_small") for p in "abcde"] + [Path("/d/x/fern")]
    ids = scene_ids_for(paths)
    assert ids == [f"{p}__colmap_small" for p in "abcde"] + ["fern"]
    # same parent names too: deeper parents, then a hash; always unique
    ids = scene_ids_for([Path("/u/a/s"), Path("/v/a/s"), Path("/w/s")])
    assert len(set(ids)) == 3 and ids[2] == "w__s" and ids[0] == "u__a__s"


@pytest.fixture(scope="module")
def base(harness, tmp_path_factory):
    """One tiny run of the sample scene (its own copy of the folder: a test edits it)."""
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("base")
    scene = write_sample_scene(root / "scenes" / "sample", seed=0, **SAMPLE_KW)
    store = root / "store"
    state = _run([scene], store)
    assert state.is_completed(), state.message
    return Path(scene), store


def test_other_folder_with_the_same_name_never_takes_over_a_scene(base, tmp_path):
    import shutil

    from freescale_core.store.store import Store

    scene, store = base
    other = tmp_path / "elsewhere" / "sample"
    shutil.copytree(scene, other)
    (other / "images" / sorted(os.listdir(other / "images"))[0]).touch()
    st = Store(store)
    before = st.read_status("sample")
    state = _run([other], store)
    assert state.is_completed(), state.message
    assert "1 scenes ok, 0 already complete" in state.message  # not "already complete"
    assert st.read_status("sample")["updated_at"] == before["updated_at"]
    assert st.read_status("sample")["source"] == str(scene)
    assert st.read_status("elsewhere__sample")["source"] == str(other)
    assert set(st.scene_ids()) == {"sample", "elsewhere__sample"}


def test_a_second_run_on_a_scene_being_written_exits_with_a_clear_message(base):
    """Two runs on one scene: while one holds the scene's writer lock, another (a different
    config, --force) touches nothing of the scene and fails naming the holder; afterwards
    the scene is as the first run left it."""
    import subprocess
    import sys
    import time

    from freescale_core.store.store import Store

    scene, store = base
    st = Store(store)
    before = st.read_status("sample")
    version = st.current_version_dir("sample").name
    ready = Path(store).parent / "holder.ready"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time, pathlib\n"
        "from freescale_core.store.store import Store\n"
        f"with Store({str(store)!r}).scene_writer('sample'):\n"
        f"    pathlib.Path({str(ready)!r}).write_text('x')\n"
        "    time.sleep(120)\n")], env=dict(os.environ, PYTHONPATH=str(REPO)))
    try:
        for _ in range(600):
            if ready.exists():
                break
            time.sleep(0.1)
        assert ready.exists()
        state = _run([scene], store, force=True,
                     config=_cfg(**{"recon.max_iterations": 60}))
        assert state.is_failed()
        assert "being written by another run" in state.message
        assert f"pid {holder.pid}" in state.message
        after = st.read_status("sample")
        assert after["updated_at"] == before["updated_at"]
        assert after["config_hash"] == before["config_hash"]
        assert st.current_version_dir("sample").name == version
    finally:
        holder.kill()
        holder.wait()
    state = _run([scene], store)  # the lock died with its holder
    assert state.is_completed() and "already complete" in state.message, state.message


def test_edited_input_reruns_ingest_even_without_force(base):
    """Last in this module: edits the base scene's images."""
    import numpy as np
    from PIL import Image

    from freescale_core.store.store import Store

    scene, store = base
    st = Store(store)
    key0 = json.loads((st.work_dir("sample") / "ingest.done.json").read_text())["key"]
    state = _run([scene], store)
    assert "already complete" in state.message and "0 scenes ok" in state.message
    img = sorted((scene / "images").iterdir())[0]
    a = np.asarray(Image.open(img)).copy()
    a[:8, :8] = 255 - a[:8, :8]
    Image.fromarray(a).save(img)
    state = _run([scene], store)
    assert state.is_completed(), state.message
    assert "1 scenes ok" in state.message
    key1 = json.loads((st.work_dir("sample") / "ingest.done.json").read_text())["key"]
    assert key1 != key0


def test_cli_bad_set_and_missing_paths_write_nothing(tmp_path, capsys):
    from flows.cli import main

    store = tmp_path / "store"
    rc = main(["run", str(tmp_path / "nope"), "--store", str(store), "--preset", "fast",
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "scene folder not found" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) <= 3
    assert not (store / "run_config.json").exists()
    (tmp_path / "s").mkdir()
    rc = main(["run", str(tmp_path / "s"), "--store", str(store), "--preset", "fast",
               "--set", "select.grid.resolution=banana", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "invalid config" in err and "select.grid.resolution" in err
    assert not (store / "run_config.json").exists()


def test_cli_run_config_absolute_merged_and_typo_free(base, tmp_path, capsys, monkeypatch):
    """A typo among good paths: one-line error, the others run, resume does not replay it;
    run_config.json keeps earlier runs' scenes as absolute paths."""
    import shutil

    from flows.cli import main

    scene, store0 = base
    store = tmp_path / "store"
    shutil.copytree(store0, store)
    monkeypatch.chdir(scene.parent)
    rc = main(["run", "sample", "typo_scene", "--store", str(store), "--preset", "fast",
               "--no-progress", *[x for kv in TINY_SET_PAIRS for x in ("--set", kv)]])
    err = capsys.readouterr().err
    assert rc == 1 and "typo_scene" in err and "Traceback" not in err
    rcfg = json.loads((store / "run_config.json").read_text())
    # earlier runs' folders are kept (other tests of this module ran on the same base store)
    assert str(scene) in rcfg["scenes"] and not any("typo_scene" in x for x in rcfg["scenes"])
    monkeypatch.chdir(tmp_path)
    assert main(["resume", str(store), "--no-progress"]) == 0
    assert "typo_scene" not in capsys.readouterr().err
