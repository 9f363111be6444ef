"""Contract tests of the store: atomic writes, version swap, concurrent status updates."""

from __future__ import annotations

import multiprocessing as mp

import numpy as np
import pyarrow.parquet as pq
import pytest
from hypothesis import given, settings, strategies as st

from freescale_core.store.store import (
    Store, atomic_path, write_json_atomic,
)
from freescale_core.errors import StoreError
from freescale_core.store.layout import graph_table, views_table, world_from_cam_column


def test_atomic_path_keeps_old_file_on_error(tmp_path):
    p = tmp_path / "a.json"
    write_json_atomic(p, {"v": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(p) as tmp:
            tmp.write_text('{"v": 2, "half')
            raise RuntimeError("crash mid-write")
    assert p.read_text().count('"v": 1') == 1
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.json"]  # no temp left behind


def _views(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = rng.normal(size=(n, 3))
    return views_table({
        "view_id": np.arange(n), "kind": ["train"] * n, "mode": ["train"] * n,
        "disposition": ["train"] * n, "world_from_cam": T, "fx": rng.uniform(100, 200, n),
        "fy": rng.uniform(100, 200, n), "cx": np.full(n, 32.0), "cy": np.full(n, 24.0),
        "width": np.full(n, 64), "height": np.full(n, 48),
    }), T


def test_publish_swaps_versions_atomically(tmp_path):
    store = Store(tmp_path / "s")
    t1, _ = _views(3)
    with store.publish("a") as out:
        pq.write_table(t1, out / "views.parquet")
        pq.write_table(graph_table([0], [1], [0.5]), out / "view_graph.parquet")
    assert store.views("a").num_rows == 3
    # A failing publication leaves version 1 intact and no staging folder behind.
    with pytest.raises(ValueError):
        with store.publish("a") as out:
            pq.write_table(_views(5)[0], out / "views.parquet")
            raise ValueError("stage crashed")
    assert store.views("a").num_rows == 3
    assert not list(store.scene_dir("a").glob(".staging-*"))
    with store.publish("a") as out:
        pq.write_table(_views(7)[0], out / "views.parquet")
    assert store.views("a").num_rows == 7
    assert store.current_version_dir("a").name == "v0002"


def test_unpublished_scene_raises(tmp_path):
    with pytest.raises(StoreError, match="no published outputs"):
        Store(tmp_path).views("nope")


@settings(max_examples=20, deadline=None)
@given(n=st.integers(1, 40), seed=st.integers(0, 2**31))
def test_views_pose_round_trip(tmp_path_factory, n, seed):
    t, T = _views(n, seed)
    p = tmp_path_factory.mktemp("v") / "views.parquet"
    pq.write_table(t, p)
    back = world_from_cam_column(pq.read_table(p))
    np.testing.assert_array_equal(back, T)


def test_views_table_requires_columns():
    with pytest.raises(StoreError, match="missing columns"):
        views_table({"view_id": [0]})


def _worker(args):
    root, i = args
    Store(root).update_status(f"scene{i % 4}", status="running", counts={f"n_w{i}": i})


def test_concurrent_status_updates_lose_nothing(tmp_path):
    root = str(tmp_path / "s")
    with mp.get_context("spawn").Pool(2) as pool:
        pool.map(_worker, [(root, i) for i in range(16)])
    store = Store(root)
    assert store.scene_ids() == ["scene0", "scene1", "scene2", "scene3"]
    for i in range(16):
        assert store.read_status(f"scene{i % 4}")["counts"][f"n_w{i}"] == i
    m = store.manifest().to_pylist()
    assert [r["scene_id"] for r in m] == store.scene_ids()
    assert all(r["status"] == "running" for r in m)


def test_manifest_flattens_counts_and_seconds(tmp_path):
    store = Store(tmp_path)
    store.update_status("a", status="ok", counts={"n_images": 9}, seconds={"recon": 1.5, "grid": 0.5})
    store.update_status("b", status="failed", error="scene 'b': boom [x.jpg]", error_type="CorruptImageError")
    rows = {r["scene_id"]: r for r in store.manifest().to_pylist()}
    assert rows["a"]["n_images"] == 9 and rows["a"]["seconds_total"] == 2.0
    assert rows["b"]["status"] == "failed" and "x.jpg" in rows["b"]["error"]
    with pytest.raises(StoreError):
        store.update_status("a", status="weird")


def test_stage_checkpoint_requires_key_and_files(tmp_path):
    store = Store(tmp_path)
    assert store.stage_done("a", "grid", "k1") is None
    assert not store.work_dir("a").exists()  # reading creates no folders
    w = store.work_dir("a", create=True)
    (w / "grid.npz").write_bytes(b"x")
    store.mark_stage_done("a", "grid", "k1", ["grid.npz"])
    assert store.stage_done("a", "grid", "k1") is not None
    assert store.stage_done("a", "grid", "k2") is None  # config/code changed
    (w / "grid.npz").unlink()
    assert store.stage_done("a", "grid", "k1") is None  # output gone


def test_status_updates_do_not_rebuild_the_manifest(tmp_path, monkeypatch):
    """update_status costs one status file, whatever the number of scenes (the manifest was
    rebuilt on every call: quadratic in scenes); the manifest is compiled when read."""
    store = Store(tmp_path)
    calls = []
    real = Store.compile_manifest
    monkeypatch.setattr(Store, "compile_manifest", lambda self: (calls.append(1), real(self)))
    for i in range(30):
        for stage in ("ingest", "recon", "select"):
            store.update_status(f"s{i:02d}", status="running", stage=stage)
    assert calls == []
    rows = store.manifest().to_pylist()
    assert len(calls) == 1 and [r["status"] for r in rows] == ["running"] * 30
    store.manifest()
    assert len(calls) == 1  # fresh: not compiled again
    store.update_status("s05", status="ok", stage="done")
    assert {r["scene_id"]: r["status"] for r in store.manifest().to_pylist()}["s05"] == "ok"
    assert len(calls) == 2


def test_stale_staging_folders_of_dead_processes_are_removed_at_publish(tmp_path):
    """A kill during publish leaves .staging-*; the next publish removes it, but never the
    folder of a live process (issue 12 #9)."""
    import subprocess
    import sys

    from freescale_core.store.store import _HOST, Store

    st = Store(tmp_path)
    sdir = st.scene_dir("s")
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    dead = sdir / f".staging-{_HOST}-{p.pid}-abc"
    live = sdir / f".staging-{_HOST}-1-abc"  # pid 1 is alive
    old_style = sdir / ".staging-xyz"  # unknown owner, fresh: kept
    for d in (dead, live, old_style):
        d.mkdir(parents=True)
        (d / "views.parquet").write_bytes(b"half")
    with st.publish("s") as out:
        (out / "x").write_text("1")
    left = sorted(x.name for x in sdir.glob(".staging-*"))
    assert left == sorted([live.name, old_style.name])
    assert (st.current_version_dir("s") / "x").read_text() == "1"
