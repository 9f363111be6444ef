"""Fault injection: every bad input, crash and real-tool quirk of issue 12, end to end.

    python benchmarks/faults.py            # every case (~10-20 min on 2 busy cores)
    python benchmarks/faults.py --quick    # the cases that need no reconstruction (< 60 s)
    python benchmarks/faults.py --cases zero_free_views,memory_guard --json

Builds each case in a temp folder from the procedural sample scene (and a copy of a shared
real scene when ``../shared/datasets`` is present), runs the ``freescale`` CLI on it as a user
would (a subprocess; fast preset made tiny; one Prefect test server for all), and prints one
row per case:

    case | expected | observed (exit code, status, first line of the message) |
    others ok | store readable | nothing half-written | verdict

verdict: ``survived`` (correct result), ``clear error`` (refused with a one-line error that
names the scene / file / setting) or ``FAIL``. Exit code 1 when any row is FAIL.
``store readable``: the manifest compiles and every ok scene's views / graph / arrays open;
``nothing half-written``: no ``.staging-*`` folder, no temporary file, no scene left
``running``/``pending``, every ``CURRENT`` names a complete version.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

SAMPLE_KW = dict(n_views=24, width=96, height=72)
TINY = ["recon.max_iterations=80", "recon.min_iterations=40", "recon.densify_from=20",
        "recon.densify_until=60", "recon.densify_every=20", "recon.max_long_side=64",
        "recon.cap_gaussians=2000", "freeview.final.target=10"]
TINY_SET = [x for kv in TINY for x in ("--set", kv)]


@dataclass
class Row:
    case: str
    expected: str
    kind: str = "survived"  # what a pass is called
    rc: int | None = None
    status: str = ""
    message: str = ""
    others_ok: bool | None = None
    readable: bool | None = None
    clean: bool | None = None
    check: bool = False
    notes: list[str] = field(default_factory=list)

    @property
    def verdict(self) -> str:
        good = (self.check and self.readable is not False and self.clean is not False
                and self.others_ok is not False)
        return self.kind if good else "FAIL"


# --------------------------------------------------------------------------- helpers
class Env:
    def __init__(self, root: Path, api_url: str | None):
        self.root = root
        self.env = dict(os.environ, PREFECT_SERVER_ANALYTICS_ENABLED="false",
                        PYTHONPATH=str(REPO), COLUMNS="200")
        if api_url:
            self.env["PREFECT_API_URL"] = api_url
        self._n = 0

    def tmp(self, name: str) -> Path:
        self._n += 1
        d = self.root / f"{self._n:02d}_{name}"
        d.mkdir(parents=True)
        return d

    def sample(self, dst: Path, seed: int = 0) -> Path:
        from freescale_core.scene.sample import write_sample_scene

        cache = self.root / f"_sample_{seed}"
        if not cache.is_dir():
            write_sample_scene(cache, seed=seed, **SAMPLE_KW)
        shutil.copytree(cache, dst)
        return dst

    def cli(self, *args: str, timeout: float = 900, cwd: Path | None = None
            ) -> tuple[int, str, str]:
        p = subprocess.run([sys.executable, "-m", "flows.cli", *args], cwd=cwd or REPO,
                           env=self.env, capture_output=True, text=True, timeout=timeout)
        return p.returncode, p.stdout, p.stderr

    def run(self, scenes: list[Path | str], store: Path, *extra: str, **kw):
        return self.cli("run", *[str(s) for s in scenes], "--store", str(store), "--preset",
                        "fast", "--no-progress", *TINY_SET, *extra, **kw)


def first_line(s: str) -> str:
    for ln in s.strip().splitlines():
        ln = ln.strip()
        if ln.startswith("error:") or ln.startswith("warning:") or "failed" in ln:
            return ln[:160]
    lines = [ln for ln in s.strip().splitlines() if ln.strip()]
    return lines[-1][:160] if lines else ""


def status_of(store: Path, sid: str) -> dict:
    from freescale_core.store.store import Store

    return Store(store).read_status(sid)


def store_health(store: Path) -> tuple[bool, bool, list[str]]:
    """(readable, clean, problems)."""
    from freescale_core.store.store import Store

    problems = []
    if not store.exists():
        return True, True, []
    st = Store(store)
    readable = True
    try:
        rows = st.manifest().to_pylist()
        for r in rows:
            if r["status"] == "ok":
                st.views(r["scene_id"])
                st.view_graph(r["scene_id"])
                st.arrays(r["scene_id"])["freeviews/rgb"].shape  # noqa: B018
    except Exception as e:  # noqa: BLE001
        readable = False
        problems.append(f"unreadable: {type(e).__name__}: {e}")
        rows = []
    clean = True
    for p in store.rglob("*"):
        if p.name.startswith(".staging-") or ".tmp-" in p.name:
            clean = False
            problems.append(f"left behind: {p.relative_to(store)}")
    for r in rows:
        if r["status"] in ("running", "pending"):
            clean = False
            problems.append(f"{r['scene_id']} left {r['status']}")
    return readable, clean, problems


def finish(row: Row, store: Path | None) -> Row:
    if store is not None:
        row.readable, row.clean, probs = store_health(store)
        row.notes += probs
    return row


# --------------------------------------------------------------------------- cases
def case_markup_error(E: Env) -> Row:
    """A failed scene whose error ends in [<path>]: the CLI prints the manifest and hint."""
    row = Row("error_with_path", "exit 1, failed scene named with its file; manifest and "
              "resume hint printed; shards ls works", "clear error")
    d = E.tmp("markup")
    good = E.sample(d / "good")
    bad = E.sample(d / "bad")
    img = sorted((bad / "images").iterdir())[3]
    img.write_bytes(img.read_bytes()[:200])
    store = d / "store"
    rc, out, err = E.run([good, bad], store)
    st = status_of(store, "bad")
    rc2, out2, err2 = E.cli("shards", "ls", str(store))
    row.rc, row.status, row.message = rc, st.get("status", ""), st.get("error", "")[:160]
    row.others_ok = status_of(store, "good").get("status") == "ok"
    row.check = (rc == 1 and st.get("status") == "failed" and img.name in st.get("error", "")
                 and "MarkupError" not in err + err2 and "resume" in err
                 and "manifest" in out and "failed" in out
                 and rc2 == 0 and "bad" in out2 and "failed" in out2)
    if not row.check:
        row.notes.append(f"rc={rc} rc2={rc2} err={err[-300:]!r} out2={out2[-300:]!r}")
    return finish(row, store)


def case_zero_free_views(E: Env) -> Row:
    row = Row("zero_free_views", "status ok, n_free_views=0, empty_reason with numbers, "
              "warning printed, freeviews/rgb shape (0,H,W,3)")
    d = E.tmp("zero")
    s = E.sample(d / "sample")
    store = d / "store"
    rc, out, err = E.run([s], store, "--set", "select.nms.max_views=0")
    from freescale_core.store.store import Store

    st = Store(store)
    r = {x["scene_id"]: x for x in st.manifest().to_pylist()}.get("sample", {})
    shape = tuple(st.arrays("sample")["freeviews/rgb"].shape) if r.get("status") == "ok" else ()
    row.rc, row.status = rc, f"{r.get('status')} n_free_views={r.get('n_free_views')}"
    row.message = r.get("empty_reason", "")
    row.check = (rc == 0 and r.get("n_free_views") == 0
                 and str(r.get("empty_reason", "")).startswith("0 free views:")
                 and "0 free views" in err + out and len(shape) == 4 and shape[0] == 0)
    return finish(row, store)


def case_far_gaussians(E: Env) -> Row:
    """A user PLY whose reconstruction threw 30% of its Gaussians 100x out."""
    import numpy as np

    from freescale_core.scene.gaussians import Gaussians
    from freescale_core.scene.ply import read_ply, write_ply

    row = Row("far_gaussians_ply", "certainty box bounded by cameras + points; free views > 0")
    d = E.tmp("far")
    s = E.sample(d / "sample")
    store0 = d / "store0"
    E.run([s], store0)
    g = read_ply(store0 / "scenes" / "sample" / "_work" / "gaussians.ply")
    rng = np.random.default_rng(0)
    n = len(g)
    k = int(0.43 * n)  # 30% of the total
    c = g.means.mean(axis=0)
    ext = float(np.linalg.norm(g.means.max(axis=0) - g.means.min(axis=0)))
    dirs = rng.normal(size=(k, 3))
    far = c + dirs / np.linalg.norm(dirs, axis=1, keepdims=True) * ext * 100
    pick = rng.integers(0, n, k)
    g2 = Gaussians(np.concatenate([g.means, far]), np.concatenate([g.log_scales, g.log_scales[pick]]),
                   np.concatenate([g.quats_wxyz, g.quats_wxyz[pick]]),
                   np.concatenate([g.opacity_logits, np.full(k, 4.0, np.float32)]),
                   np.concatenate([g.sh, g.sh[pick]]))
    write_ply(s / "gaussians.ply", g2)
    store = d / "store"
    rc, out, err = E.run([s], store)
    st = status_of(store, "sample")
    nf = st.get("counts", {}).get("n_free_views")
    row.rc, row.status = rc, f"{st.get('status')} n_free_views={nf}"
    row.message = (st.get("info", {}).get("empty_reason") or first_line(err + out))
    from freescale_core.store.store import Store

    try:
        a = Store(store).arrays("sample")["certainty"].attrs
        diag = float(np.linalg.norm(np.subtract(a["bbox_max"], a["bbox_min"])))
        row.notes.append(f"box diagonal {diag:.2f} vs Gaussian extent {ext:.2f} "
                         f"(far ones at {100 * ext:.0f})")
        row.check = rc == 0 and st.get("status") == "ok" and (nf or 0) > 0 and diag < 10 * ext
    except Exception as e:  # noqa: BLE001
        row.notes.append(str(e))
    return finish(row, store)


def case_id_collision(E: Env) -> Row:
    row = Row("scene_id_collision", "3 folders named 'sample' -> 3 distinct ids, a later "
              "different folder never 'already complete' with another's results")
    d = E.tmp("ids")
    a = E.sample(d / "a" / "sample")
    b = E.sample(d / "b" / "sample", seed=1)
    c = E.sample(d / "c" / "sample", seed=2)
    store = d / "store"
    rc1, _, err1 = E.run([a, b], store)
    rc2, out2, err2 = E.run([c], store)
    from freescale_core.store.store import Store

    st = Store(store)
    src = {sid: st.read_status(sid).get("source") for sid in st.scene_ids()}
    row.rc, row.status = rc2, json.dumps(sorted(src))
    row.message = first_line(out2 + err2)
    row.check = (rc1 == 0 and rc2 == 0 and sorted(src.values()) == sorted(map(str, (a, b, c)))
                 and len(src) == 3 and "1 scenes ok" in out2)
    return finish(row, store)


def case_edited_input(E: Env) -> Row:
    import numpy as np
    from PIL import Image

    row = Row("edited_input", "a changed image re-runs the scene (ingest key changes)")
    d = E.tmp("edit")
    s = E.sample(d / "sample")
    store = d / "store"
    E.run([s], store)
    k0 = json.loads((store / "scenes/sample/_work/ingest.done.json").read_text())["key"]
    img = sorted((s / "images").iterdir())[0]
    a = np.asarray(Image.open(img)).copy()
    a[:10, :10] = 0
    Image.fromarray(a).save(img)
    rc, out, err = E.run([s], store)
    k1 = json.loads((store / "scenes/sample/_work/ingest.done.json").read_text())["key"]
    row.rc, row.status, row.message = rc, status_of(store, "sample").get("status"), first_line(out)
    row.check = rc == 0 and k1 != k0 and "1 scenes ok" in out
    return finish(row, store)


def case_iteration_order(E: Env) -> Row:
    import numpy as np

    from freescale_core.scene.ply import read_ply, write_ply

    row = Row("3dgs_iteration_order", "point_cloud/iteration_30000 used, not iteration_7000")
    d = E.tmp("iter")
    s = E.sample(d / "sample")
    store0 = d / "store0"
    E.run([s], store0)
    g = read_ply(store0 / "scenes/sample/_work/gaussians.ply")
    for it, sub in ((7000, g.subset(np.arange(len(g) // 2)) if hasattr(g, "subset") else None),
                    (30000, g)):
        p = s / "point_cloud" / f"iteration_{it}" / "point_cloud.ply"
        p.parent.mkdir(parents=True)
        if sub is None:
            p.write_bytes(b"not a ply")  # picking this one would fail the scene
        else:
            write_ply(p, sub)
    store = d / "store"
    rc, out, err = E.run([s], store)
    st = status_of(store, "sample")
    ng = st.get("counts", {}).get("n_gaussians")
    row.rc, row.status, row.message = rc, f"{st.get('status')} n_gaussians={ng}", first_line(out + err)
    row.check = rc == 0 and ng == len(g)
    return finish(row, store)


def _ns_scene(E: Env, dst: Path, rot_decimals: int | None = None, **meta_over) -> Path:
    """The sample scene as a nerfstudio transforms.json scene (pinhole)."""
    import numpy as np
    import pycolmap

    from freescale_core.scene.io import load_scene
    from freescale_core.scene.io.nerfstudio import transforms_dict

    src = E.sample(dst.parent / (dst.name + "_colmap"))
    sc = load_scene(src)
    shutil.copytree(src / "images", dst / "images")
    cams = [pycolmap.Camera(model="PINHOLE", width=int(sc.cameras.width[i]),
                            height=int(sc.cameras.height[i]),
                            params=np.array([sc.cameras.fx[i], sc.cameras.fy[i],
                                             sc.cameras.cx[i], sc.cameras.cy[i]]))
            for i in range(len(sc))]
    meta = transforms_dict(list(sc.image_names), sc.cameras.world_from_cam, cams)
    meta.update(meta_over)
    (dst / "transforms.json").write_text(json.dumps(meta, indent=1))
    shutil.rmtree(src)
    return dst


def case_path_traversal(E: Env) -> Row:
    row = Row("path_traversal", "file_path '../..' refused naming frame and path; other "
              "scene ok", "clear error")
    d = E.tmp("traversal")
    ns = _ns_scene(E, d / "ns")
    secret = d / "secret.png"
    shutil.copy(sorted((ns / "images").iterdir())[0], secret)
    meta = json.loads((ns / "transforms.json").read_text())
    meta["frames"][0]["file_path"] = "../secret.png"
    (ns / "transforms.json").write_text(json.dumps(meta))
    good = E.sample(d / "good")
    store = d / "store"
    rc, out, err = E.run([ns, good], store)
    st = status_of(store, "ns")
    row.rc, row.status, row.message = rc, st.get("status"), st.get("error", "")[:160]
    row.others_ok = status_of(store, "good").get("status") == "ok"
    row.check = (rc == 1 and st.get("status") == "failed" and "outside the scene folder"
                 in st.get("error", "") and "../secret.png" in st.get("error", ""))
    return finish(row, store)


def case_bad_set(E: Env) -> Row:
    row = Row("bad_set", "exit 2, one-line error naming the setting, nothing written",
              "clear error")
    d = E.tmp("badset")
    s = E.sample(d / "sample")
    store = d / "store"
    rc, out, err = E.cli("run", str(s), "--store", str(store), "--preset", "fast",
                         "--set", "select.grid.resolution=banana", "--no-progress")
    row.rc, row.message = rc, first_line(err)
    row.check = (rc == 2 and "select.grid.resolution" in err and "Traceback" not in err
                 and not store.exists())
    return finish(row, store)


def case_missing_path(E: Env) -> Row:
    row = Row("missing_path", "exit 2, one line, nothing written (run_config untouched)",
              "clear error")
    d = E.tmp("missing")
    store = d / "store"
    rc, out, err = E.cli("run", str(d / "no_such_scene"), "--store", str(store), "--preset",
                         "fast", "--no-progress")
    row.rc, row.message = rc, first_line(err)
    row.check = (rc == 2 and len(err.strip().splitlines()) <= 3 and "Traceback" not in err
                 and not (store / "run_config.json").exists())
    return finish(row, store)


def case_typo_among_good(E: Env) -> Row:
    row = Row("typo_among_good", "exit 1, typo named on one line, other scene ok, "
              "run_config absolute and without the typo, resume from elsewhere ok",
              "clear error")
    d = E.tmp("typo")
    E.sample(d / "sample")
    store = d / "store"
    rc, out, err = E.cli("run", "sample", "smaple", "--store", str(store), "--preset", "fast",
                         "--no-progress", *TINY_SET, cwd=d)
    rcfg = json.loads((store / "run_config.json").read_text()) if (store / "run_config.json").is_file() else {}
    rc2, out2, err2 = E.cli("resume", str(store), "--no-progress", cwd=Path(tempfile.gettempdir()))
    row.rc, row.message = rc, first_line(err)
    row.status = status_of(store, "sample").get("status", "")
    row.others_ok = row.status == "ok"
    row.check = (rc == 1 and "smaple" in err and "Traceback" not in err
                 and rcfg.get("scenes") == [str((d / "sample").resolve())] and rc2 == 0)
    return finish(row, store)


def case_memory_guard(E: Env) -> Row:
    row = Row("memory_guard", "grid.resolution=1024 refused before anything runs, with the "
              "estimate (exit 2); the stage refuses too (scene named)", "clear error")
    d = E.tmp("mem")
    s = E.sample(d / "sample")
    store = d / "store"
    rc, out, err = E.cli("run", str(s), "--store", str(store), "--preset", "fast",
                         "--set", "select.grid.resolution=1024", "--no-progress")
    row.rc, row.message = rc, first_line(err)
    row.check = (rc == 2 and "select.grid.resolution=1024" in err and "GB" in err
                 and "Traceback" not in err and not store.exists())
    return finish(row, store)


def case_stale_staging_and_sigterm(E: Env) -> Row:
    """SIGTERM mid-run marks the scene failed (interrupted); a staging folder left by a dead
    publisher is removed by the resume's publish; the resumed store is complete."""
    row = Row("sigterm_and_stale_staging", "SIGTERM -> exit 130, scene failed 'interrupted'; "
              "resume removes the dead .staging-*, ends ok")
    from freescale_core.store.store import _HOST

    d = E.tmp("sigterm")
    s = E.sample(d / "sample")
    store = d / "store"
    p = subprocess.Popen([sys.executable, "-m", "flows.cli", "run", str(s), "--store",
                          str(store), "--preset", "fast", "--no-progress", *TINY_SET],
                         cwd=REPO, env=E.env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 600 and p.poll() is None:
        if status_of(store, "sample").get("stage") == "reconstruct":
            break
        time.sleep(0.1)
    p.send_signal(signal.SIGTERM)
    try:
        out, err = p.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        p.kill()
        out, err = p.communicate()
    st = status_of(store, "sample")
    row.notes.append(f"after SIGTERM: rc={p.returncode} status={st.get('status')}")
    if p.returncode != 130:
        row.notes.append(f"stderr tail: {err[-600:]!r}")
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = store / "scenes" / "sample" / f".staging-{_HOST}-{dead.pid}-x"
    stale.mkdir(parents=True)
    (stale / "views.parquet").write_bytes(b"half")
    rc2, out2, err2 = E.cli("resume", str(store), "--no-progress")
    st2 = status_of(store, "sample")
    row.rc, row.status = p.returncode, f"{st.get('status')} -> resume {st2.get('status')}"
    row.message = st.get("error", "")[:160]
    row.check = (p.returncode == 130 and st.get("status") == "failed"
                 and "interrupted" in st.get("error", "") and rc2 == 0
                 and st2.get("status") == "ok" and not stale.exists())
    return finish(row, store)


KILL_POINTS = (("ingest", 0.0), ("reconstruct", 0.3), ("select", 0.0), ("freeviews", 0.1),
               ("publish", 0.0), ("reconstruct", 2.0))


def _kill_when(store: Path, sid: str, point: str, p: subprocess.Popen, limit: float = 900
               ) -> bool:
    """Wait until the run reaches ``point`` (a stage running, or ``publish``: a staging
    folder exists); False when the run ended first."""
    sdir = store / "scenes" / sid
    t0 = time.monotonic()
    while time.monotonic() - t0 < limit and p.poll() is None:
        if point == "publish":
            if sdir.is_dir() and any(sdir.glob(".staging-*")):
                return True
            time.sleep(0.005)
            continue
        st = status_of(store, sid) if (sdir / "status.json").is_file() else {}
        if st.get("status") == "running" and st.get("stage") == point:
            return True
        time.sleep(0.02)
    return False


def case_kill_resume(E: Env, points=KILL_POINTS) -> Row:
    """SIGKILL the CLI at each point (a stage running, + a delay; or while publish builds its
    staging folder), resume; the published store equals an uninterrupted run's every time."""
    row = Row("kill_then_resume", f"SIGKILL at {len(points)} points (each stage, during "
              "publish), resume: store equals an uninterrupted run (store_diff.py)")
    d = E.tmp("kill")
    s = E.sample(d / "sample")
    ref = d / "ref"
    E.run([s], ref)
    same = []
    for k, (point, delay) in enumerate(points):
        store = d / f"k{k}_{point}"
        p = subprocess.Popen([sys.executable, "-m", "flows.cli", "run", str(s), "--store",
                              str(store), "--preset", "fast", "--no-progress", *TINY_SET],
                             cwd=REPO, env=E.env, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True)
        hit = _kill_when(store, "sample", point, p)
        time.sleep(delay)
        killed = p.poll() is None
        if killed:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait()
        left = [x.name for x in (store / "scenes" / "sample").glob(".staging-*")]
        rc, _, _ = E.cli("resume", str(store), "--no-progress")
        diff = subprocess.run([sys.executable, str(REPO / "benchmarks" / "store_diff.py"),
                               str(ref), str(store)], capture_output=True, text=True)
        same.append(diff.returncode == 0 and rc == 0)
        row.notes.append(f"{point}+{delay:g}s: {'killed' if killed and hit else 'ran to the end'}"
                         f"{', staging left' if left else ''}, resume rc={rc}, "
                         f"store_diff rc={diff.returncode}")
        r, c, probs = store_health(store)
        row.readable = r if row.readable is None else (row.readable and r)
        row.clean = c if row.clean is None else (row.clean and c)
        row.notes += probs
    row.rc, row.status = 0, f"{sum(same)}/{len(same)} equal"
    row.message = "; ".join(row.notes[:6])
    row.check = all(same)
    return row


def case_instant_ngp(E: Env) -> Row:
    from freescale_core.scene.fixtures import write_instant_ngp_scene

    row = Row("instant_ngp_capture", "rotations to 6 decimals, OPENCV k1, no points, "
              "aabb_scale, sharpness, 2 absent frames: ok with free views and warnings")
    d = E.tmp("ngp")
    s = E.sample(d / "sample")
    ngp = write_instant_ngp_scene(s, d / "ngp", n_absent=2)
    store = d / "store"
    rc, out, err = E.run([ngp], store, "--set", "recon.max_iterations=300")
    st = status_of(store, "ngp")
    nf = st.get("counts", {}).get("n_free_views")
    w = st.get("info", {}).get("ingest_warnings", "")
    row.rc, row.status = rc, f"{st.get('status')} n_free_views={nf}"
    row.message = w[:160] or st.get("error", "")[:160]
    row.check = (rc == 0 and st.get("status") == "ok" and (nf or 0) > 0 and "absent" in w
                 and "aabb_scale" in w and "sharpness" in w)
    return finish(row, store)


def case_size_outlier(E: Env) -> Row:
    from PIL import Image

    row = Row("image_size_outlier", "one 8x6 image among full-size ones: failed naming the "
              "file and both sizes; the other scene ok", "clear error")
    d = E.tmp("outlier")
    s = E.sample(d / "thumb")
    img = sorted((s / "images").iterdir())[5]
    Image.open(img).resize((8, 6)).save(img)
    good = E.sample(d / "good")
    store = d / "store"
    rc, out, err = E.run([s, good], store)
    st = status_of(store, "thumb")
    row.rc, row.status, row.message = rc, st.get("status"), st.get("error", "")[:160]
    row.others_ok = status_of(store, "good").get("status") == "ok"
    row.check = (rc == 1 and "outlier" in st.get("error", "") and img.name in st.get("error", ""))
    return finish(row, store)


def case_ply_other_frame(E: Env) -> Row:
    import dataclasses

    import numpy as np

    from freescale_core.scene.ply import read_ply, write_ply

    row = Row("ply_other_frame", "a PLY normalised like gsplat's normalize_world_space: "
              "refused with PSNR, extent ratio and the likely cause", "clear error")
    d = E.tmp("frame")
    s = E.sample(d / "sample")
    store0 = d / "store0"
    E.run([s], store0)
    g = read_ply(store0 / "scenes/sample/_work/gaussians.ply")
    c = g.means.mean(axis=0)
    k = 1.0 / float(np.abs(g.means - c).max())
    g2 = dataclasses.replace(g, means=((g.means - c) * k).astype(np.float32),
                             log_scales=(g.log_scales + np.log(k)).astype(np.float32))
    write_ply(s / "gaussians.ply", g2)
    store = d / "store"
    rc, out, err = E.run([s], store)
    st = status_of(store, "sample")
    row.rc, row.status, row.message = rc, st.get("status"), st.get("error", "")[:160]
    e = st.get("error", "")
    row.check = rc == 1 and "PSNR" in e and "extent" in e and "another frame" in e
    return finish(row, store)


def case_masks(E: Env) -> Row:
    from freescale_core.scene.turntable import write_turntable_scene

    row = Row("masks", "turntable captures with masks (COLMAP masks/ as <name>.png, nerfstudio "
              "mask_path): ok with free views, masks used (Gaussians outside the masks counted)")
    d = E.tmp("masks")
    tt = write_turntable_scene(d / "tt_colmap", **SAMPLE_KW, mask_naming="name_png")
    ns = write_turntable_scene(d / "tt_ns", **SAMPLE_KW, fmt="nerfstudio")
    store = d / "store"
    rc, out, err = E.run([tt, ns], store, "--set", "recon.max_iterations=300")
    st = [status_of(store, sid) for sid in ("tt_colmap", "tt_ns")]
    nf = [s.get("counts", {}).get("n_free_views") for s in st]
    row.rc, row.status = rc, " / ".join(f"{s.get('status')} n_free_views={n}"
                                         for s, n in zip(st, nf))
    row.message = first_line(out + err)
    row.check = rc == 0 and all(s.get("status") == "ok" and (n or 0) > 0 for s, n in zip(st, nf))
    try:
        import pickle

        for sid in ("tt_colmap", "tt_ns"):
            sel = pickle.loads((store / "scenes" / sid / "_work" / "selection.pkl").read_bytes())
            k = sel.counts.get("n_gaussians_outside_masks")
            row.notes.append(f"{sid}: {k} Gaussians outside the masks left out of the grid")
            row.check = row.check and k is not None
    except Exception as e:  # noqa: BLE001
        row.notes.append(f"selection unreadable: {e}")
        row.check = False
    return finish(row, store)


def case_mask_errors(E: Env) -> Row:
    import cv2
    import numpy as np

    from freescale_core.scene.turntable import write_turntable_scene

    row = Row("mask_errors", "one mask missing in masks/, one mask of another size: both "
              "failed naming the file; a good masked scene ok", "clear error")
    d = E.tmp("mask_errors")
    part = write_turntable_scene(d / "partial", **SAMPLE_KW)
    (part / "masks" / "frame_00007.png").unlink()
    size = write_turntable_scene(d / "size", **SAMPLE_KW, fmt="nerfstudio")
    cv2.imwrite(str(size / "masks" / "frame_00003.png"), np.zeros((10, 10), np.uint8))
    good = write_turntable_scene(d / "good", **SAMPLE_KW)
    store = d / "store"
    rc, out, err = E.run([part, size, good], store)
    a, b = status_of(store, "partial"), status_of(store, "size")
    row.rc = rc
    row.status = f"{a.get('status')} / {b.get('status')}"
    row.message = f"{a.get('error', '')[:110]} | {b.get('error', '')[:110]}"
    row.others_ok = status_of(store, "good").get("status") == "ok"
    row.check = (rc == 1 and "frame_00007.png" in a.get("error", "")
                 and "partly masked" in a.get("error", "")
                 and "frame_00003.png" in b.get("error", "") and "10x10" in b.get("error", ""))
    return finish(row, store)


CASES = {
    "error_with_path": case_markup_error,
    "zero_free_views": case_zero_free_views,
    "far_gaussians_ply": case_far_gaussians,
    "scene_id_collision": case_id_collision,
    "edited_input": case_edited_input,
    "3dgs_iteration_order": case_iteration_order,
    "path_traversal": case_path_traversal,
    "bad_set": case_bad_set,
    "missing_path": case_missing_path,
    "typo_among_good": case_typo_among_good,
    "memory_guard": case_memory_guard,
    "instant_ngp_capture": case_instant_ngp,
    "image_size_outlier": case_size_outlier,
    "ply_other_frame": case_ply_other_frame,
    "sigterm_and_stale_staging": case_stale_staging_and_sigterm,
    "kill_then_resume": case_kill_resume,
    "masks": case_masks,
    "mask_errors": case_mask_errors,
}
QUICK = ("bad_set", "missing_path", "memory_guard")  # no Prefect server, no reconstruction


def run_cases(names: list[str], api_url: str | None, root: Path) -> list[Row]:
    E = Env(root, api_url)
    rows = []
    for n in names:
        t0 = time.perf_counter()
        try:
            r = CASES[n](E)
        except Exception as e:  # noqa: BLE001 - a crash of the case is a FAIL row
            r = Row(n, "-", message=f"case crashed: {type(e).__name__}: {e}"[:160])
        r.notes.append(f"{time.perf_counter() - t0:.0f} s")
        rows.append(r)
        print(f"[{n}] {r.verdict} ({r.notes[-1]})", file=sys.stderr, flush=True)
    return rows


def print_table(rows: list[Row]) -> None:
    def b(x):
        return "-" if x is None else ("yes" if x else "NO")

    hdr = ["case", "expected", "observed", "others ok", "store readable",
           "nothing half-written", "verdict"]
    print("| " + " | ".join(hdr) + " |")
    print("|" + "---|" * len(hdr))
    for r in rows:
        obs = f"rc={r.rc} {r.status} {r.message}".replace("|", "/").replace("\n", " ")
        print(f"| {r.case} | {r.expected} | {obs.strip()} | {b(r.others_ok)} | "
              f"{b(r.readable)} | {b(r.clean)} | **{r.verdict}** |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK)}")
    ap.add_argument("--cases", default="", help="comma-separated case names")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--keep", action="store_true", help="keep the temp folder")
    a = ap.parse_args(argv)
    names = [c for c in a.cases.split(",") if c] or (list(QUICK) if a.quick else list(CASES))
    bad = [n for n in names if n not in CASES]
    if bad:
        print(f"error: unknown case(s) {bad}; known: {', '.join(CASES)}", file=sys.stderr)
        return 2
    root = Path(tempfile.mkdtemp(prefix="freescale-faults-"))
    try:
        if all(n in QUICK for n in names):
            rows = run_cases(names, None, root)
        else:
            from prefect.testing.utilities import prefect_test_harness

            with prefect_test_harness(server_startup_timeout=180):
                from prefect.settings import PREFECT_API_URL

                rows = run_cases(names, PREFECT_API_URL.value(), root)
    finally:
        if not a.keep:
            shutil.rmtree(root, ignore_errors=True)
    if a.json:
        for r in rows:
            print(json.dumps({**r.__dict__, "verdict": r.verdict}, default=str))
    else:
        print_table(rows)
        for r in rows:
            if r.notes[:-1]:
                print(f"- {r.case}: " + "; ".join(r.notes[:-1]))
    return 0 if all(r.verdict != "FAIL" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
