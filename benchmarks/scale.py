"""How the store's bookkeeping grows with the number of scenes.

Builds stores of N tiny scenes (published versions written directly by the store API: a
status, a CURRENT pointer and a one-row views table per scene; no pipeline stage runs) and
times, for each N:

* ``manifest``: compiling ``manifest.parquet`` from every ``status.json`` (cold: stale);
* ``scenes_ls``: what ``freescale scenes ls STORE`` reads (the manifest, fresh);
* ``resume_plan``: the scenes ``freescale resume`` would re-run (every status read, not-ok
  kept);
* ``pack_plan``: the scenes ``freescale shards pack`` would pack (every ok scene's CURRENT
  resolved to its version).

then fits ``t = a * N^k`` (least squares in log-log) and prints the exponent ``k`` and the
peak resident memory. ``--store-url s3://bucket/prefix`` runs the same on an object store
(credentials and endpoint from the environment).

    python -m benchmarks.scale --sizes 100 1000 10000

``--orchestration`` instead times the Prefect flow ``generate-dataset`` itself over N empty
scene folders with every stage's work stubbed (``FREESCALE_NOOP_STAGES=1``, see
``tasks/stage.py``: the five tasks per scene are still submitted, tracked and logged, and
their store bookkeeping runs), with each runner (``threads``, and ``dask``: a LocalCluster on
127.0.0.1), each (runner, N) in a fresh process with its own temporary Prefect server and
Prefect home. It reports the flow's seconds per scene, the marginal seconds per scene between
the two largest N, the exponent of ``t ~ N^k``, the peak RSS of the flow's process, of the
Prefect server and of the Dask workers (sampled every 0.2 s), and the server's share of the
CPU time of all of them while the flow ran:

    python -m benchmarks.scale --orchestration --sizes 10 100 1000

``--share-server`` exports the temporary server's address (``PREFECT_API_URL``) before the
flow, so that Dask workers report to it instead of each starting a server of its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np



def build(root: str, n: int) -> None:
    """``n`` scenes, each ok with one published version (written without the pipeline)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from freescale_core.store.store import Store

    st = Store(root)
    for i in range(n):
        sid = f"s{i:05d}"
        with st.publish(sid) as out:
            pq.write_table(pa.table({"view_id": [0]}), out / "views.parquet")
        ver = st.current_version_dir(sid).name
        st.update_status(sid, status="ok" if i % 10 else "failed", version=ver,
                         counts={"n_free_views": i % 7}, seconds={"publish": 0.01})


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def measure(root: str) -> dict:
    from freescale_core.store.store import Store

    st = Store(root)
    t_man, _ = timed(lambda: (st.compile_manifest(), st.manifest())[1])
    t_ls, rows = timed(lambda: Store(root).manifest().to_pylist())
    t_res, todo = timed(lambda: [s for s in Store(root).scene_ids()
                                 if Store(root).read_status(s).get("status") != "ok"])
    s2 = Store(root)
    t_pack, vers = timed(lambda: {r["scene_id"]: r["version"] for r in s2.manifest().to_pylist()
                                  if r["status"] == "ok"})
    return {"manifest": t_man, "scenes_ls": t_ls, "resume_plan": t_res, "pack_plan": t_pack,
            "n_rows": len(rows), "n_todo": len(todo), "n_pack": len(vers)}


def fit_exponent(ns, ts) -> float:
    k, _ = np.polyfit(np.log(np.asarray(ns, float)), np.log(np.maximum(ts, 1e-9)), 1)
    return float(k)


# --------------------------------------------------------------------------- orchestration
SERVER_MARK = "prefect.server.api.server:create_app"


class _Sampler:
    """Peak RSS and last CPU seconds of this process and its descendants, by role."""

    def __init__(self, period: float = 0.2):
        import threading

        import psutil

        self.me = psutil.Process()
        self.peak = {"flow": 0, "server": 0, "workers": 0}
        self.cpu: dict[int, tuple[str, float]] = {}
        self.servers: set[int] = set()  # pids of every Prefect server seen
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, args=(period,), daemon=True)

    def role(self, p) -> str | None:
        if p.pid == self.me.pid:
            return "flow"
        try:
            cmd = " ".join(p.cmdline())
        except Exception:  # noqa: BLE001 - gone
            return None
        if SERVER_MARK in cmd:
            return "server"
        if "flows.reaper" in cmd:
            return None
        return "workers"

    def sample(self) -> None:
        per = {"flow": 0, "server": 0, "workers": 0}
        for p in [self.me, *self.me.children(recursive=True)]:
            r = self.role(p)
            if r is None:
                continue
            if r == "server":
                self.servers.add(p.pid)
            try:
                per[r] += p.memory_info().rss
                c = p.cpu_times()
                self.cpu[p.pid] = (r, c.user + c.system)
            except Exception:  # noqa: BLE001 - exited between the listing and the read
                pass
        for r, v in per.items():
            self.peak[r] = max(self.peak[r], v)

    def cpu_by_role(self) -> dict[str, float]:
        out = {"flow": 0.0, "server": 0.0, "workers": 0.0}
        for r, c in self.cpu.values():
            out[r] += c
        return out

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            self.sample()

    def __enter__(self):
        self.sample()
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.sample()


def orchestration_one(runner: str, n: int, workers: int, tmp: str,
                      share_server: bool = False) -> dict:
    """One flow run over ``n`` empty scene folders (in this process; see ``main``)."""
    assert os.environ.get("FREESCALE_NOOP_STAGES") == "1"
    from prefect import flow

    from flows.generate_dataset import generate_dataset
    from flows.reaper import install
    from schemas.pipeline import PipelineConfig

    install()  # the temporary server dies with this process
    scenes = Path(tmp) / "scenes"
    for i in range(n):
        (scenes / f"s{i:05d}").mkdir(parents=True)

    @flow(name="warm-up")
    def warm_up() -> int:  # starts the temporary server outside the timed part
        return 1

    warm_up()
    if share_server:  # Dask workers inherit the address of this process's temporary server
        from prefect.server.api.server import SubprocessASGIServer

        (srv,) = [s for s in SubprocessASGIServer._instances.values() if s.running]
        os.environ["PREFECT_API_URL"] = srv.api_url
    with _Sampler() as smp:
        cpu0 = smp.cpu_by_role()
        t0 = time.perf_counter()
        summary = generate_dataset(scenes=[str(scenes / "*")], store=str(Path(tmp) / "store"),
                                   config=PipelineConfig.from_preset("fast"),
                                   scale_out=runner, n_workers=workers)
        wall = time.perf_counter() - t0
        smp.sample()
        cpu1 = smp.cpu_by_role()
    if len(summary["ok"]) != n:
        raise SystemExit(f"orchestration run: {len(summary['ok'])} of {n} scenes ok")
    cpu = {r: cpu1[r] - cpu0.get(r, 0.0) for r in cpu1}
    total = sum(cpu.values()) or 1e-9
    return {"runner": runner + ("+shared-server" if share_server else ""), "n_scenes": n, "workers": workers, "flow_s": wall,
            "s_per_scene": wall / n, "peak_rss_flow_mb": smp.peak["flow"] / 2**20,
            "peak_rss_server_mb": smp.peak["server"] / 2**20,
            "peak_rss_workers_mb": smp.peak["workers"] / 2**20,
            **{f"cpu_{r}_s": v for r, v in cpu.items()}, "server_cpu_share": cpu["server"] / total,
            "n_servers": len(smp.servers)}


def orchestration(sizes: list[int], runners: list[str], workers: int, as_json: bool,
                  share_server: bool = False) -> int:
    import subprocess

    rows = []
    for runner in runners:
        for n in sizes:
            with tempfile.TemporaryDirectory(prefix="fs-orch-") as tmp:
                env = {**os.environ, "FREESCALE_NOOP_STAGES": "1",
                       "PREFECT_HOME": f"{tmp}/prefect", "XDG_CACHE_HOME": f"{tmp}/cache",
                       "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
                       "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "300"}
                env.pop("PREFECT_API_URL", None)  # a temporary server of its own
                p = subprocess.run([sys.executable, "-m", "benchmarks.scale", "--_orch-one",
                                    runner, str(n), str(workers), tmp,
                                    *(["--share-server"] if share_server else [])],
                                   env=env, capture_output=True, text=True)
                if p.returncode != 0:
                    print(f"error: {runner} N={n}: {p.stderr.strip()[-2000:]}", file=sys.stderr)
                    return 1
                r = json.loads(p.stdout.strip().splitlines()[-1])
            rows.append(r)
            print(json.dumps(r) if as_json else
                  f"{r['runner']:7s} N={n:6d}  flow {r['flow_s']:8.1f} s  {r['s_per_scene']:.3f} s/scene"
                  f"  peak RSS flow {r['peak_rss_flow_mb']:.0f} MB, server "
                  f"{r['peak_rss_server_mb']:.0f} MB, workers {r['peak_rss_workers_mb']:.0f} MB"
                  f"  server CPU share {100 * r['server_cpu_share']:.0f} %"
                  f" ({r['n_servers']} server process{'es' if r['n_servers'] > 1 else ''})",
                  flush=True)
    for runner in dict.fromkeys(r["runner"] for r in rows):
        rr = [r for r in rows if r["runner"] == runner]
        if len(rr) > 1:
            k = fit_exponent([r["n_scenes"] for r in rr], [r["flow_s"] for r in rr])
            a, b = rr[-2], rr[-1]
            marg = (b["flow_s"] - a["flow_s"]) / (b["n_scenes"] - a["n_scenes"])
            print(f"{runner}: growth exponent k (flow seconds ~ N^k) {k:.2f}; marginal "
                  f"{marg:.3f} s/scene between N={a['n_scenes']} and N={b['n_scenes']}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=None,
                    help="numbers of scenes (default: 100 1000 10000; --orchestration: "
                         "10 100 1000)")
    ap.add_argument("--store-url", default=None,
                    help="object-store prefix (default: a local temporary folder)")
    ap.add_argument("--orchestration", action="store_true",
                    help="time the generate-dataset flow with no-op stages instead")
    ap.add_argument("--runners", nargs="+", default=["threads", "dask"],
                    choices=["threads", "dask"], help="with --orchestration")
    ap.add_argument("--workers", type=int, default=2, help="with --orchestration")
    ap.add_argument("--share-server", action="store_true",
                    help="with --orchestration: export the temporary server's address before "
                         "the flow, so that Dask workers report to it instead of starting "
                         "servers of their own")
    ap.add_argument("--_orch-one", nargs=4, dest="orch_one", help=argparse.SUPPRESS)
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.orch_one:
        runner, n, w, tmp = a.orch_one
        print(json.dumps(orchestration_one(runner, int(n), int(w), tmp, a.share_server)),
              flush=True)
        return 0
    if a.orchestration:
        return orchestration(a.sizes or [10, 100, 1000], a.runners, a.workers, a.json,
                             a.share_server)
    a.sizes = a.sizes or [100, 1000, 10000]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.sizes:
            root = (f"{a.store_url.rstrip('/')}/n{n}" if a.store_url else f"{tmp}/n{n}")
            t_build, _ = timed(lambda: build(root, n))
            r = {"n_scenes": n, "build_s": t_build, **measure(root)}
            r["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            rows.append(r)
            print(json.dumps(r) if a.json else
                  f"N={n:6d}  manifest {r['manifest']:.3f} s  scenes ls {r['scenes_ls']:.3f} s"
                  f"  resume plan {r['resume_plan']:.3f} s  pack plan {r['pack_plan']:.3f} s"
                  f"  peak RSS {r['peak_rss_mb']:.0f} MB  (build {t_build:.1f} s)", flush=True)
    if len(rows) > 1:
        ns = [r["n_scenes"] for r in rows]
        ks = {k: fit_exponent(ns, [r[k] for r in rows])
              for k in ("manifest", "scenes_ls", "resume_plan", "pack_plan")}
        print("growth exponent k (t ~ N^k): " + ", ".join(f"{k} {v:.2f}" for k, v in ks.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
