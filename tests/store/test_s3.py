"""The store on object storage, against a real S3 API: moto's server on 127.0.0.1, started
and stopped by the fixture (no traffic leaves loopback)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import uuid
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

pytest.importorskip("s3fs", reason="s3fs is not installed (the dev extra installs it)")
moto_server = pytest.importorskip("moto.server",
                                  reason="moto[server] is not installed (the dev extra installs it)")

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def s3():
    """Environment of a moto S3 server on 127.0.0.1 (credentials are moto's dummies)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    srv = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    srv.start()
    env = {"AWS_ENDPOINT_URL": f"http://127.0.0.1:{port}", "AWS_ACCESS_KEY_ID": "testing",
           "AWS_SECRET_ACCESS_KEY": "testing", "AWS_DEFAULT_REGION": "us-east-1"}
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    import s3fs

    import urllib.request

    # moto's state lives in this process, shared by every server it starts: start clean
    urllib.request.urlopen(urllib.request.Request(f"{env['AWS_ENDPOINT_URL']}/moto-api/reset",
                                                  method="POST"), timeout=30).close()
    s3fs.S3FileSystem.clear_instance_cache()
    s3fs.S3FileSystem().mkdir("bucket")
    try:
        yield env
    finally:
        srv.stop()
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _url() -> str:
    return f"s3://bucket/{uuid.uuid4().hex[:8]}"


def _other_process(st, tmp_path):
    """The same store as another worker sees it: a mirror folder of its own."""
    from freescale_core.store.store import Store

    o = Store(st.url)
    o.root = tmp_path / f"mirror-{uuid.uuid4().hex[:6]}"
    o.root.mkdir()
    return o


def test_url_store_publish_and_read(s3, tmp_path):
    from freescale_core.store.store import ObjectStore
    from freescale_core.store.store import Store

    st = Store(_url())
    assert isinstance(st, ObjectStore)
    assert not list(Path(".").glob("s3:*"))  # no local folder named after the URL
    st.update_status("a", status="running")
    with st.scene_writer("a"):
        with st.publish("a") as out:
            pq.write_table(pa.table({"view_id": [0, 1, 2]}), out / "views.parquet")
            import zarr

            g = zarr.open_group(str(out / "arrays.zarr"), mode="w")
            g.create_array("x", data=np.arange(6, dtype=np.int64))
            (out / "cameras.png").write_bytes(b"\x89PNG fake")
    st.update_status("a", status="ok")
    name = st.fs.cat_file(f"{st.base}/scenes/a/CURRENT").decode()
    assert name.startswith("v0001-") and len(name) == 14
    o = _other_process(st, tmp_path)
    assert o.scene_ids() == ["a"]
    assert o.views("a").column("view_id").to_pylist() == [0, 1, 2]  # pyarrow fs layer
    assert o.arrays("a")["x"][:].tolist() == list(range(6))        # zarr fsspec store
    d = o.current_version_dir("a")  # a local copy for path readers and exports
    assert (d / "cameras.png").read_bytes() == b"\x89PNG fake"
    assert o.manifest().to_pylist()[0]["status"] == "ok"
    # a second version: new prefix, CURRENT moves, the previous is kept
    with st.scene_writer("a"), st.publish("a") as out:
        pq.write_table(pa.table({"view_id": [7]}), out / "views.parquet")
    assert o.views("a").column("view_id").to_pylist() == [7]
    assert len(st.fs.glob(f"{st.base}/scenes/a/v0*")) == 2


def test_two_writers_cannot_both_win(s3, tmp_path):
    """Both build a version from the same CURRENT; the conditional PUT lets one win, the
    other fails naming the winner, and the winner's version is intact."""
    from freescale_core.store.objstore import CommitConflictError
    from freescale_core.store.store import Store

    st = Store(_url())
    o = _other_process(st, tmp_path)
    ready = threading.Barrier(2)
    results: dict = {}

    def write(store, tag):
        try:
            with store.publish("s") as out:
                (out / "who.txt").write_text(tag)
                ready.wait(timeout=30)  # both staged from "no version"
            results[tag] = "won"
        except CommitConflictError as e:
            results[tag] = str(e)

    ts = [threading.Thread(target=write, args=(s, t)) for s, t in ((st, "A"), (o, "B"))]
    [t.start() for t in ts]
    [t.join(60) for t in ts]
    won = [t for t, r in results.items() if r == "won"]
    assert len(won) == 1, results
    lost = ({"A", "B"} - set(won)).pop()
    assert "another writer published" in results[lost] and "scene 's'" in results[lost]
    d = _other_process(st, tmp_path).current_version_dir("s")
    assert (d / "who.txt").read_text() == won[0]


def test_scene_writer_lease(s3, tmp_path, monkeypatch):
    from freescale_core.store import objstore
    from freescale_core.store.store import SceneBusyError, Store

    st = Store(_url())
    o = _other_process(st, tmp_path)
    with st.scene_writer("s"):
        with pytest.raises(SceneBusyError, match=r"scene 's' in s3://.* is being written"):
            with o.scene_writer("s"):
                pass
    with o.scene_writer("s"):  # released: the next writer gets it
        pass
    # an expired lease (its holder died) is taken over
    lease = f"{st.base}/scenes/s/.writer.lease"
    st.fs.pipe_file(lease, json.dumps({"token": "dead", "owner": "pid 1 on gone",
                                       "expires": 0}).encode())
    with o.scene_writer("s"):
        assert json.loads(st.fs.cat_file(lease))["token"] != "dead"
    assert not st.fs.exists(lease)


def test_lease_without_conditional_writes(tmp_path):
    """A backend without conditional writes (fsspec's memory filesystem): check, write,
    read back."""
    from freescale_core.store.objstore import _Precondition, put_conditional
    from freescale_core.store.store import SceneBusyError, Store

    st = Store(f"memory://fs-{uuid.uuid4().hex[:6]}")
    put_conditional(st.fs, f"{st.base}/x", b"1", "*")
    with pytest.raises(_Precondition):
        put_conditional(st.fs, f"{st.base}/x", b"2", "*")
    with st.scene_writer("s"):
        with pytest.raises(SceneBusyError):
            with Store(st.url).scene_writer("s"):
                pass


# --------------------------------------------------------------------------- a real run
TINY = ("from tests.conftest import TINY_OVERRIDES as O\n"
        "from schemas.pipeline import PipelineConfig\n"
        "from tasks import scene_tasks as T\n"
        "from freescale_core.store.store import config_hash\n"
        "cfg = PipelineConfig.from_preset('fast', O)\n")


def _run_stages(url: str, scene: Path, kill_at_commit: bool = False) -> subprocess.CompletedProcess:
    """Every stage of one scene in a fresh process (its own mirror folder); with
    ``kill_at_commit`` the process dies after uploading its version, before CURRENT."""
    code = TINY + (
        "import os\n"
        "from freescale_core.store import store as objstore\n"
        "put = objstore.put_conditional\n"
        "def die(fs, path, data, match):\n"
        "    if path.endswith('/CURRENT'): os._exit(9)\n"
        "    return put(fs, path, data, match)\n"
        "objstore.put_conditional = die\n" if kill_at_commit else "") + (
        f"st, p, sid = {url!r}, {str(scene)!r}, 'sample'\n"
        "i = T.ingest.fn(st, sid, p, cfg)\n"
        "r = T.reconstruct.fn(st, i, p, cfg)\n"
        "s = T.select.fn(st, i, r, cfg)\n"
        "f = T.freeviews.fn(st, i, r, s, p, cfg)\n"
        "T.publish.fn(st, i, r, s, f, cfg, config_hash(cfg), p)\n")
    env = {**os.environ, "PYTHONPATH": str(REPO), "PREFECT_SERVER_ANALYTICS_ENABLED": "false"}
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=900)


@pytest.fixture(scope="module")
def sample_scene(tmp_path_factory):
    from freescale_core.scene.sample import write_sample_scene

    d = tmp_path_factory.mktemp("s3scene") / "sample"
    write_sample_scene(d, n_views=30, width=96, height=72, seed=0)
    return d


def test_kill_mid_publish_then_resume(s3, sample_scene, tmp_path):
    """A run killed between its version upload and the CURRENT PUT leaves no visible version;
    a fresh process (no shared folder) resumes from the stage checkpoints in the bucket."""
    from freescale_core.store.store import Store

    url = _url()
    p = _run_stages(url, sample_scene, kill_at_commit=True)
    assert p.returncode == 9, p.stderr[-2000:]
    st = Store(url)
    st.root = tmp_path / "mirror"
    assert st.current_version_dir("sample") is None  # nothing half-visible
    assert st.read_status("sample")["status"] == "running"
    done = {s: st.stage_result("sample", s) is not None for s in ("ingest", "reconstruct")}
    assert all(done.values()), done
    rec = json.loads(st.fs.cat_file(f"{st.base}/scenes/sample/_work/reconstruct.done.json"))
    p = _run_stages(url, sample_scene)
    assert p.returncode == 0, p.stderr[-2000:]
    # the reconstruction was not recomputed: its checkpoint record is the killed run's
    assert json.loads(st.fs.cat_file(
        f"{st.base}/scenes/sample/_work/reconstruct.done.json")) == rec
    status = st.read_status("sample")
    assert status["status"] == "ok" and status["version"].startswith("v0002-")
    d = st.current_version_dir("sample")
    assert d.name == status["version"] and (d / "views.parquet").is_file()
    assert st.manifest().to_pylist()[0]["n_free_views"] == status["counts"]["n_free_views"]
