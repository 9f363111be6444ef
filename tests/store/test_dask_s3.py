"""The Dask path with workers that share no local folder: each worker of a 127.0.0.1
LocalCluster runs in a working directory, temporary folder and store mirror of its own, and
the store URL ``s3://...`` (moto's server on 127.0.0.1, the fixture of ``test_s3.py``) is the
only place they share. The stages of the tiny sample scene alternate between the two workers,
so every stage must find the previous stage's checkpoint in the bucket; the published scene
is then listed by ``freescale scenes ls s3://...``."""

from __future__ import annotations

import json
import os
import tempfile
import uuid
from pathlib import Path

import pytest

pytest.importorskip("distributed", reason="dask.distributed is not installed")
from tests.store.test_s3 import s3  # noqa: E402,F401 - the fixture

# smaller than tests.conftest.TINY_OVERRIDES: this test is about where bytes go, not quality
TINIER = {"recon": {"max_iterations": 40, "min_iterations": 20, "densify_from": 10,
                    "densify_until": 30, "densify_every": 10, "max_long_side": 48,
                    "cap_gaussians": 1000},
          "freeview": {"final": {"target": 6}}}


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    d = tmp_path_factory.mktemp("daskscene") / "sample"
    write_sample_scene(d, n_views=20, width=64, height=48, seed=0)
    return d


def _isolate(base: str, dask_worker=None) -> str:
    """Give this worker process a folder of its own: cwd, TMPDIR and the store mirror."""
    d = tempfile.mkdtemp(prefix=f"worker-{dask_worker.name}-", dir=base)
    os.chdir(d)
    os.environ["TMPDIR"] = d
    os.environ["FREESCALE_MIRROR_DIR"] = d
    tempfile.tempdir = d
    return d


def _stage(name: str, url: str, args: tuple) -> tuple:
    """One stage's task function on this worker: (its result, cwd, this worker's mirror)."""
    from schemas.pipeline import PipelineConfig
    from tasks import scene_tasks as T
    from freescale_core.store.store import Store, config_hash

    cfg = PipelineConfig.from_preset("fast", TINIER)
    fn = {"ingest": T.ingest, "reconstruct": T.reconstruct, "select": T.select,
          "freeviews": T.freeviews, "publish": T.publish}[name].fn
    if name == "publish":
        args = (*args[:4], cfg, config_hash(cfg), args[4])
    else:
        args = (*args, cfg)
    return fn(url, *args), os.getcwd(), str(Store(url).root)


def test_dask_workers_share_only_the_bucket(s3, tiny_scene, tmp_path, capsys):
    from distributed import Client, LocalCluster

    from flows.cli import main

    url = f"s3://bucket/dask-{uuid.uuid4().hex[:8]}"
    base = tmp_path / "workers"
    base.mkdir()
    p = str(tiny_scene)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, worker_dashboard_address=None) as cluster, \
            Client(cluster) as client:
        dirs = client.run(_isolate, str(base))  # {worker address: its folder}
        w0, w1 = sorted(dirs)
        assert dirs[w0] != dirs[w1]

        def on(worker, name, *args):
            return client.submit(_stage, name, url, args, workers=[worker],
                                 allow_other_workers=False, pure=False).result()

        i, *where_i = on(w0, "ingest", "sample", p)
        r, *where_r = on(w1, "reconstruct", i, p)
        s, *where_s = on(w0, "select", i, r)
        f, *where_f = on(w1, "freeviews", i, r, s, p)
        out, *where_p = on(w0, "publish", i, r, s, f, p)
    assert out == {"scene_id": "sample", "status": "ok"}
    # each stage ran in its worker's own folder, mirror inside it; nothing written elsewhere
    for (cwd, mirror), w in zip((where_i, where_r, where_s, where_f, where_p),
                                (w0, w1, w0, w1, w0)):
        assert cwd == dirs[w] and mirror.startswith(dirs[w] + "/"), (cwd, mirror, dirs[w])
    # the reconstruction ran on w1; w0's selection got its Gaussians from the bucket
    m0 = Path(where_s[1]) / "scenes" / "sample" / "_work"
    assert (m0 / "gaussians.ply").is_file() and (m0 / "scene.pkl").is_file()
    capsys.readouterr()
    assert main(["scenes", "ls", url, "--json"]) == 0
    rows = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [(r["scene_id"], r["status"]) for r in rows] == [("sample", "ok")]
    assert rows[0]["version"].startswith("v0001-") and "n_free_views" in rows[0]
