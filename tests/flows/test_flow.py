"""generate-dataset end to end, with prefect_test_harness: failures, resume, kill, Dask.

One module-scoped reference store (threads runner, uninterrupted) holds three scenes: the
sample scene, a second sample scene and a copy of kermit; the other tests compare to it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from schemas.pipeline import PipelineConfig
from tests.conftest import real_scene_dir

os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"
REPO = Path(__file__).resolve().parents[2]
SAMPLE_KW = dict(n_views=30, width=96, height=72)
# The fast preset, made smaller still so that seven scene runs fit in a test suite.
TINY = {"recon": {"max_iterations": 80, "min_iterations": 40, "densify_from": 20,
                  "densify_until": 60, "densify_every": 20, "max_long_side": 64,
                  "cap_gaussians": 2000},
        "freeview": {"final": {"target": 10}}}
TINY_SET = ["--set", "recon.max_iterations=80", "--set", "recon.min_iterations=40",
            "--set", "recon.densify_from=20", "--set", "recon.densify_until=60",
            "--set", "recon.densify_every=20", "--set", "recon.max_long_side=64",
            "--set", "recon.cap_gaussians=2000", "--set", "freeview.final.target=10"]


@pytest.fixture(scope="module")
def harness():
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        from prefect.settings import PREFECT_API_URL

        yield PREFECT_API_URL.value()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    root = tmp_path_factory.mktemp("scenes")
    write_sample_scene(root / "sample_a", seed=0, **SAMPLE_KW)
    write_sample_scene(root / "sample_b", seed=1, **SAMPLE_KW)
    shutil.copytree(real_scene_dir("kermit"), root / "kermit")
    return root


def run(harness, scene_dirs, store, **kw):
    from flows.generate_dataset import generate_dataset

    return generate_dataset(scenes=[str(s) for s in scene_dirs], store=str(store),
                            config=PipelineConfig.from_preset("fast", TINY), return_state=True,
                            **kw)


def comparable(store: Path, sid: str):
    """A scene's manifest row and views table, timing columns and timestamps dropped."""
    from freescale_core.store.store import Store

    st = Store(store)
    row = {k: v for k, v in next(r for r in st.manifest().to_pylist() if r["scene_id"] == sid).items()
           if "second" not in k and k not in ("updated_at", "source")}
    row.pop("info", None)
    views = st.views(sid).to_pydict()
    return _nan_free(row), _nan_free(views)


def _nan_free(x):
    """NaN -> None, so that equal tables compare equal."""
    if isinstance(x, dict):
        return {k: _nan_free(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_free(v) for v in x]
    if isinstance(x, float) and x != x:
        return None
    return x


@pytest.fixture(scope="module")
def reference_store(harness, scenes, tmp_path_factory):
    """Threads runner: one scene broken (corrupt image), then fixed and resumed."""
    store = tmp_path_factory.mktemp("ref") / "store"
    img = scenes / "kermit" / "images" / "kermit003.jpg"
    good = img.read_bytes()
    img.write_bytes(good[: len(good) // 3])  # truncated JPEG
    state = run(harness, [scenes / "sample_a", scenes / "sample_b", scenes / "kermit"], store)
    first = {"state": state}
    from freescale_core.store.store import Store

    st = Store(store)
    first["status"] = {s: st.read_status(s) for s in st.scene_ids()}
    img.write_bytes(good)
    state2 = run(harness, [scenes / "sample_a", scenes / "sample_b", scenes / "kermit"], store)
    return store, first, state2


def test_failed_scene_reported_others_finish(reference_store):
    store, first, _ = reference_store
    assert first["state"].is_failed()
    assert "kermit" in first["state"].message
    st = first["status"]
    assert st["sample_a"]["status"] == "ok" and st["sample_b"]["status"] == "ok"
    assert st["kermit"]["status"] == "failed"
    assert "kermit003.jpg" in st["kermit"]["error"] and "kermit" in st["kermit"]["error"]


def test_resume_reruns_only_the_failed_scene(reference_store):
    from freescale_core.store.store import Store

    store, first, state2 = reference_store
    assert state2.is_completed(), state2.message
    st = Store(store)
    for sid in ("sample_a", "sample_b"):  # untouched by the second run
        assert st.read_status(sid)["updated_at"] == first["status"][sid]["updated_at"]
        assert st.current_version_dir(sid).name == "v0001"
    rows = {r["scene_id"]: r for r in st.manifest().to_pylist()}
    assert all(r["status"] == "ok" for r in rows.values())
    assert rows["kermit"]["n_images"] == 9
    # end to end: free views exist, with their images in zarr
    for sid in rows:
        views = st.views(sid)
        disp = views.column("disposition").to_pylist()
        assert disp.count("train") == rows[sid]["n_images"]
        # every NMS-selected candidate was rendered and scored (and reserve candidates
        # while the stage was short of its target)
        rendered = [d for d in disp if d in ("free_view", "rejected")]
        assert len(rendered) >= rows[sid]["n_selected"] > 0
        if sid.startswith("sample"):
            assert "free_view" in disp
        # every kept view satisfies the thresholds recorded beside it
        t = views.to_pydict()
        for i, d in enumerate(disp):
            if d == "free_view":
                assert t["black_ratio"][i] <= t["thr_black_ratio"][i]
                assert t["brisque"][i] < t["thr_brisque"][i]
                assert t["depth_validity"][i] > t["thr_depth_validity"][i]
                assert t["pred_psnr"][i] >= t["thr_pred_psnr"][i]  # trust (issue 19)
            if d in ("free_view", "rejected"):  # every render carries its trust scores
                assert np.isfinite(t["pred_psnr"][i]) and 0 <= t["photo_support"][i] <= 1
        if "free_view" in disp:
            rgb = st.arrays(sid)["freeviews/rgb"]
            assert rgb.shape[0] == disp.count("free_view") and rgb.dtype == np.uint8
            size = st.arrays(sid)["freeviews/size"][:]
            fi = [(t["free_index"][i], t["height"][i], t["width"][i])
                  for i, d in enumerate(disp) if d == "free_view"]
            for k, h, w in fi:  # stored pixels match the intrinsics in views.parquet
                assert tuple(size[k]) == (h, w)


def test_kill_mid_scene_then_rerun_equals_uninterrupted(harness, scenes, reference_store, tmp_path):
    store_ref = reference_store[0]
    store = tmp_path / "store"
    env = dict(os.environ, PREFECT_API_URL=harness, PREFECT_SERVER_ANALYTICS_ENABLED="false")
    cmd = [sys.executable, "-m", "flows.cli", "run", str(scenes / "sample_a"),
           "--store", str(store), "--preset", "fast", "--no-progress", *TINY_SET]
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    status = store / "scenes" / "sample_a" / "_work" / "reconstruct.done.json"
    t0 = time.monotonic()
    while not status.exists() and proc.poll() is None and time.monotonic() - t0 < 300:
        time.sleep(0.05)
    assert proc.poll() is None, "flow finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)  # mid-scene: reconstruction done, selection running
    proc.wait()
    from freescale_core.store.store import Store

    assert Store(store).read_status("sample_a")["status"] in ("running", "pending")
    state = run(harness, [scenes / "sample_a"], store)
    assert state.is_completed(), state.message
    row, views = comparable(store, "sample_a")
    row_ref, views_ref = comparable(store_ref, "sample_a")
    row.pop("version"), row_ref.pop("version")
    row.pop("config_hash"), row_ref.pop("config_hash")
    assert row == row_ref
    assert views == views_ref


def test_dask_runner_gives_the_same_store(harness, scenes, reference_store, tmp_path):
    store = tmp_path / "store"
    state = run(harness, [scenes / "sample_a", scenes / "sample_b", scenes / "kermit"], store,
                scale_out="dask", n_workers=2)
    assert state.is_completed(), state.message
    for sid in ("sample_a", "sample_b", "kermit"):
        row, views = comparable(store, sid)
        row_ref, views_ref = comparable(reference_store[0], sid)
        row.pop("version"), row_ref.pop("version")
        assert row == row_ref, sid
        assert views == views_ref, sid


def test_cli_scenes_ls_and_show(reference_store):
    store = reference_store[0]
    env = dict(os.environ, COLUMNS="200")
    out = subprocess.run([sys.executable, "-m", "flows.cli", "scenes", "ls", str(store)],
                         cwd=REPO, env=env, capture_output=True, text=True, check=True).stdout
    assert "sample_a" in out and "kermit" in out and "ok" in out
    out = subprocess.run([sys.executable, "-m", "flows.cli", "scenes", "show", str(store),
                          "sample_a"], cwd=REPO, env=env, capture_output=True, text=True,
                         check=True).stdout
    assert "free_view" in out and "train" in out


def test_cli_piped_output_is_wide_and_survives_a_closed_pipe(reference_store):
    """Piped (not a terminal, no COLUMNS): headers are not wrapped at 80 columns, and a reader
    that stops early (`| head`) is not answered with a traceback."""
    store = reference_store[0]
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    out = subprocess.run([sys.executable, "-m", "flows.cli", "scenes", "ls", str(store)],
                         cwd=REPO, env=env, capture_output=True, text=True, check=True).stdout
    assert "scene_id" in out and "n_candidates" in out
    p = subprocess.Popen([sys.executable, "-m", "flows.cli", "scenes", "show", str(store),
                          "sample_a", "--all"], cwd=REPO, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.readline()
    p.stdout.close()  # the reader goes away after one line
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) == 0 and "Traceback" not in err, err


def test_manifest_recon_columns_with_and_without_held_out_views(harness, scenes, reference_store,
                                                                  tmp_path):
    """recon_test_psnr is a float64 column in every manifest: null when every view trains
    (split "all", the default for data generation), a value with the paper's OOD split."""
    from flows.generate_dataset import generate_dataset
    from freescale_core.store.store import Store

    ref = Store(reference_store[0]).manifest()
    for col in ("recon_seconds", "recon_train_psnr", "recon_test_psnr"):
        assert str(ref.schema.field(col).type) == "double"
    rows = {r["scene_id"]: r for r in ref.to_pylist()}
    assert rows["sample_a"]["recon_test_psnr"] is None
    assert rows["sample_a"]["recon_train_psnr"] > 10 and rows["sample_a"]["recon_split"] == "all"

    store = tmp_path / "ood"
    state = generate_dataset(scenes=[str(scenes / "sample_a")], store=str(store),
                             config=PipelineConfig.from_preset("fast", {**TINY, "recon_split": "ood"}),
                             return_state=True)
    assert state.is_completed(), state.message
    row = Store(store).manifest().to_pylist()[0]
    assert row["recon_split"] == "ood" and 8 < row["recon_test_psnr"] < 60
    import json

    per_view = json.loads(row["recon_test_views"])
    assert len(per_view["views"]) == len(per_view["psnr"]) == len(per_view["ssim"]) >= 2
    assert abs(np.mean(per_view["psnr"]) - row["recon_test_psnr"]) < 0.01
    # the held-out views are kept out of every generation stage and published as `heldout`
    views = Store(store).views("sample_a").to_pydict()
    kinds = views["kind"]
    held = [n for n, k in zip(views["name"], kinds) if k == "heldout"]
    assert sorted(held) == sorted(per_view["views"])
    assert row["n_train_views"] == kinds.count("train") == SAMPLE_KW["n_views"] - len(held)
    assert row["n_heldout_views"] == len(held)
    ids = set(np.asarray(views["view_id"])[np.asarray(kinds) == "heldout"].tolist())
    graph = Store(store).view_graph("sample_a").to_pydict()
    assert not ids & (set(graph["src"]) | set(graph["dst"]))


def test_a_stage_that_crashes_unrecorded_leaves_its_scene_failed(harness, scenes, tmp_path,
                                                                   monkeypatch):
    """A task that dies without the stage recording why (Prefect, a worker): its scene is
    'failed' in the store with the stage and the exception, never left 'pending'."""
    from prefect import task

    import flows.generate_dataset as G
    import tasks.stage as S

    @task(name="select")
    def crashing_select(*a, **k):
        raise RuntimeError("worker lost")

    monkeypatch.setattr(S, "NOOP_STAGES", True)  # no stage work: only the orchestration runs
    monkeypatch.setattr(G, "select", crashing_select)
    store = tmp_path / "store"
    state = run(harness, [scenes / "sample_a"], store)
    assert state.is_failed()
    from freescale_core.store.store import Store

    st = Store(store).read_status("sample_a")
    assert st["status"] == "failed" and st["error_type"] == "Crashed"
    assert "select: RuntimeError: worker lost" in st["error"] and "sample_a" in st["error"]
