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
"""

from __future__ import annotations

import argparse
import json
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 10000])
    ap.add_argument("--store-url", default=None,
                    help="object-store prefix (default: a local temporary folder)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
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
