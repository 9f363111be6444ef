"""Fault injection: every bad input, crash, real-tool quirk and careless use, end to end.

    python -m benchmarks.faults            # every case (~40-60 min on 2 busy cores)
    python -m benchmarks.faults --quick    # the cases that need no reconstruction (< 60 s)
    python -m benchmarks.faults --careless # store, shards, exports, arguments (one small store)
    python -m benchmarks.faults --cases zero_free_views,memory_guard --json

Builds each case in a temp folder from the procedural sample scene, runs the ``freescale``
CLI on it as a user would (a subprocess; fast preset made tiny; one Prefect test server for
all), and prints one row per case:

    case | expected | observed (exit code, status, first line of the message) |
    others ok | store readable | nothing half-written | verdict

verdict: ``survived`` (correct result), ``clear error`` (refused with a one-line error that
names the scene / file / setting); otherwise ``traceback`` (a Python traceback reached the
terminal), ``silent wrong data``, ``data lost`` (the case's failure kind) or ``FAIL``. Exit
code 1 when any row is neither survived nor clear error. ``--careless``: the careless-use
cases (store, shards, exports, argument checks; no reconstruction beyond one small store,
``FAULTS_PUBLISHED=DIR`` reuses it across invocations).
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
    fail_kind: str = "FAIL"  # what a failed check is: "silent wrong data", "data lost", ...
    traceback: bool = False  # a Python traceback reached the user's terminal

    @property
    def verdict(self) -> str:
        good = (self.check and self.readable is not False and self.clean is not False
                and self.others_ok is not False and not self.traceback)
        if good:
            return self.kind
        return "traceback" if self.traceback else self.fail_kind


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

    def _run_argv(self, scenes: list[Path | str], store: Path, extra) -> list[str]:
        return ["run", *[str(s) for s in scenes], "--store", str(store), "--preset", "fast",
                "--no-progress", *TINY_SET, *extra]

    def run(self, scenes: list[Path | str], store: Path, *extra: str, **kw):
        return self.cli(*self._run_argv(scenes, store, extra), **kw)

    def start_run(self, scenes: list[Path | str], store: Path, *extra: str,
                  **popen_kw) -> subprocess.Popen:
        """``freescale run`` in the background (the fault is then injected into it)."""
        return subprocess.Popen([sys.executable, "-m", "flows.cli",
                                 *self._run_argv(scenes, store, extra)],
                                cwd=REPO, env=self.env, **popen_kw)


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


def first_run_gaussians(E: Env, scene: Path, store: Path):
    """The Gaussians a first (tiny) run trains on ``scene`` (into ``store``): the base of the
    user PLYs the PLY cases tamper with."""
    from freescale_core.scene.ply import read_ply

    E.run([scene], store)
    return read_ply(store / "scenes" / scene.name / "_work" / "gaussians.ply")


def finish(row: Row, store: Path | None) -> Row:
    if store is not None:
        row.readable, row.clean, probs = store_health(store)
        row.notes += probs
    return row


# --------------------------------------------------------------------------- careless use
# Issue 58's cases: a published store (built once per invocation, without Prefect: the
# stage functions the flow runs) used as a careless user would, each a real CLI command.
def published_store(E: Env) -> Path:
    """A store with two published scenes (sample_a, sample_b), built once; copy it.
    ``FAULTS_PUBLISHED=DIR`` reuses (or builds into) DIR across invocations, the captures
    it was published from in ``DIR_src`` beside it."""
    ref = Path(os.environ.get("FAULTS_PUBLISHED") or E.root / "_published")
    srcs = ref.parent / f"{ref.name}_src"  # the captures, kept beside it (their source paths)
    if not ((ref / "scenes" / "sample_b" / "CURRENT").is_file()
            and (srcs / "sample_b" / "images").is_dir()):
        from freescale_core.store.store import config_hash
        from flows.setargs import parse_set
        from schemas.pipeline import PipelineConfig
        from tasks import scene_tasks as T

        cfg = PipelineConfig.from_preset("fast", parse_set(TINY))
        for k, sid in enumerate(("sample_a", "sample_b")):
            src = srcs / sid if (srcs / sid / "images").is_dir() else E.sample(srcs / sid, seed=k)
            st, p = str(ref), str(src)
            i = T.ingest.fn(st, sid, p, cfg)
            r = T.reconstruct.fn(st, i, p, cfg)
            sel = T.select.fn(st, i, r, cfg)
            f = T.freeviews.fn(st, i, r, sel, p, cfg)
            T.publish.fn(st, i, r, sel, f, cfg, config_hash(cfg), p)
    return ref


def store_copy(E: Env, d: Path) -> Path:
    dst = d / "store"
    shutil.copytree(published_store(E), dst)
    return dst


def tree_digest(root: Path) -> dict[str, int]:
    return {str(p.relative_to(root)): p.stat().st_size for p in root.rglob("*") if p.is_file()}


def one_line_error(rc: int, err: str, *needles: str, code: int | None = 2) -> bool:
    """Exit code non-zero (``code`` when given), the last stderr line an ``error:`` naming
    every needle, and no traceback."""
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    return (rc != 0 and (code is None or rc == code) and bool(lines)
            and lines[-1].startswith("error:") and all(n in lines[-1] for n in needles)
            and "Traceback" not in err)


def _tb(row: Row, *errs: str) -> None:
    row.traceback = row.traceback or any("Traceback (most recent call last)" in e for e in errs)


def _mount_tmpfs(d: Path, opts: str) -> bool:
    d.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(d)],
                          capture_output=True).returncode == 0


def _umount(d: Path) -> None:
    subprocess.run(["umount", str(d)], capture_output=True)


FULL_DISK_SIM = """
import errno, sys, zarr.storage
from flows.cli import main
def full(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device", {out!r})
import shutil; shutil.copyfile = full; shutil.copy2 = full
zarr.storage.LocalStore.set = lambda *a, **k: full()
sys.exit(main({argv!r}))
"""


def _cli_full_disk(E: Env, d: Path, argv: list[str], out_name: str) -> tuple[int, str, str, str]:
    """Run ``argv`` (with ``{OUT}`` replaced) writing into a full disk: a real 64 kB tmpfs
    where mounting is permitted, else a simulation (copies and zarr writes raise ENOSPC)."""
    mnt = d / "full"
    if _mount_tmpfs(mnt, "size=64k"):
        try:
            out = mnt / out_name
            rc, o, e = E.cli(*[x.replace("{OUT}", str(out)) for x in argv])
            return rc, o, e, "real 64 kB tmpfs"
        finally:
            _umount(mnt)
    out = mnt / out_name
    args = [x.replace("{OUT}", str(out)) for x in argv]
    p = subprocess.run([sys.executable, "-c", FULL_DISK_SIM.format(out=str(out), argv=args)],
                       cwd=REPO, env=E.env, capture_output=True, text=True, timeout=900)
    return p.returncode, p.stdout, p.stderr, "simulated (ENOSPC on every copy / zarr write)"


def case_pack_into_store(E: Env) -> Row:
    row = Row("pack_into_store", "shards pack STORE STORE: one line (the store), exit 2, the "
              "store untouched", "clear error", fail_kind="data lost")
    d = E.tmp("pack_into_store")
    st = store_copy(E, d)
    before = tree_digest(st)
    rc, out, err = E.cli("shards", "pack", str(st), str(st))
    _tb(row, err)
    row.rc, row.message = rc, first_line(err)
    row.check = one_line_error(rc, err, "is a store") and tree_digest(st) == before
    return finish(row, st)


def case_pack_not_a_store(E: Env) -> Row:
    row = Row("pack_not_a_store", "shards pack on a missing path, a file, a folder that is "
              "not a store: one line naming it, exit 2 (was: 'packed 0 scene(s)', exit 0)",
              "clear error", fail_kind="silent wrong data")
    d = E.tmp("pack_not_a_store")
    (d / "afile").write_text("x")
    (d / "photos" / "images").mkdir(parents=True)
    ok, msgs = True, []
    for src in (d / "missing", d / "afile", d / "photos"):
        rc, out, err = E.cli("shards", "pack", str(src), str(d / "out"))
        _tb(row, err)
        ok = ok and one_line_error(rc, err, str(src)) and "packed 0" not in out
        msgs.append(f"rc={rc}")
    row.rc, row.status, row.message = rc, " ".join(msgs), first_line(err)
    row.check = ok
    return row


def case_pack_twice_and_user_folder(E: Env) -> Row:
    row = Row("pack_scenes_twice_user_folder", "--scenes a a packs a once; a user's "
              "OUT/shards/my_photos/ survives; the same scene from a second store keeps both "
              "manifest rows; shards verify passes", fail_kind="data lost")
    from freescale_core.store.shards import read_manifest

    d = E.tmp("pack_twice")
    st = store_copy(E, d)
    other = d / "other" / "store"
    shutil.copytree(st, other)
    out = d / "sh"
    (out / "shards" / "my_photos").mkdir(parents=True)
    (out / "shards" / "my_photos" / "a.jpg").write_bytes(b"jpeg")
    rc1, o1, e1 = E.cli("shards", "pack", str(st), str(out), "--scenes", "sample_a", "sample_a",
                        "--resolution", "32")
    rc2, o2, e2 = E.cli("shards", "pack", str(other), str(out), "--scenes", "sample_a",
                        "--resolution", "32")
    rc3, o3, e3 = E.cli("shards", "verify", str(out))
    _tb(row, e1, e2, e3)
    rows = read_manifest(out).to_pylist() if (out / "manifest.parquet").is_file() else []
    keys = sorted((r["source_store"], r["scene_id"]) for r in rows)
    row.rc, row.status = rc3, f"{len(rows)} manifest rows"
    row.message = first_line(o3)
    row.check = (rc1 == rc2 == rc3 == 0 and keys == sorted([(str(st), "sample_a"),
                                                           (str(other), "sample_a")])
                 and (out / "shards" / "my_photos" / "a.jpg").read_bytes() == b"jpeg")
    return row


def _packed(E: Env, d: Path) -> Path:
    st = store_copy(E, d)
    out = d / "sh"
    rc, o, e = E.cli("shards", "pack", str(st), str(out), "--resolution", "32")
    assert rc == 0, e
    return out


def _chunks(out: Path, what: str = "images") -> list[Path]:
    return sorted(p for p in (out / "shards" / "000000.zarr" / what).rglob("*")
                  if p.is_file() and p.name != "zarr.json")


SHARD_DAMAGE = ("truncate", "flip", "pose", "delete")


def damage_shard(out: Path, how: str) -> None:
    """Damage shard 000000 of the packed folder ``out``: ``truncate`` cuts every image chunk
    to 5 bytes, ``flip`` flips one byte of the first image chunk, ``pose`` one byte of the
    first pose chunk, ``delete`` removes the first image chunk."""
    chunks = _chunks(out, "world_from_cam" if how == "pose" else "images")
    if how == "truncate":
        for c in chunks:
            c.write_bytes(c.read_bytes()[:5])
    elif how == "delete":
        chunks[0].unlink()
    elif how in ("flip", "pose"):
        b = bytearray(chunks[0].read_bytes())
        b[len(b) // 2] ^= 0xFF
        chunks[0].write_bytes(bytes(b))
    else:
        raise ValueError(f"unknown shard damage {how!r}; known: {SHARD_DAMAGE}")


def _damaged_shard_row(E: Env, row: Row, name: str, damages: tuple[str, ...]) -> Row:
    """Pack, damage (each of ``damages`` on its own copy), then ``shards verify`` must exit 1
    naming the shard and ``train-lvsm`` exit 2 with one line naming it and its SHA-256,
    before any checkpoint is written."""
    d = E.tmp(name)
    ok, notes = True, []
    for how in damages:
        out = _packed(E, d / how)
        damage_shard(out, how)
        rc, o, err = E.cli("shards", "verify", str(out))
        run = d / how / "run"
        rc2, o2, err2 = E.cli("train-lvsm", str(out), "--steps", "1", "--out", str(run))
        _tb(row, err, err2)
        shard = str(out / "shards" / "000000.zarr")
        good = (rc == 1 and shard in err and one_line_error(rc2, err2, shard, "SHA-256")
                and not (run / "ckpt").exists())
        ok = ok and good
        notes.append(f"{how}: verify rc={rc}, train-lvsm rc={rc2}")
    row.rc, row.status, row.message = rc2, "; ".join(notes), first_line(err2)
    row.check = ok
    return row


def case_truncated_chunk(E: Env) -> Row:
    row = Row("truncated_shard_chunk", "every image chunk cut to 5 bytes: train-lvsm refuses "
              "before training naming the shard (exit 2); shards verify exit 1 naming it",
              "clear error", fail_kind="silent wrong data")
    return _damaged_shard_row(E, row, "truncated", ("truncate",))


def case_flipped_shard(E: Env) -> Row:
    row = Row("corrupt_shard_byte_pose", "one byte of an image chunk flipped / a pose chunk "
              "flipped / a chunk deleted: shards verify exit 1 naming the shard, train-lvsm "
              "refuses (was: shards ls exit 0 and black or wrong images trained on)",
              "clear error", fail_kind="silent wrong data")
    return _damaged_shard_row(E, row, "flipped", ("flip", "pose", "delete"))


def case_pack_full_disk(E: Env) -> Row:
    row = Row("pack_full_disk", "shards pack into a full disk: one line naming OUT, exit 2, no "
              "traceback", "clear error")
    d = E.tmp("pack_full")
    st = store_copy(E, d)
    rc, o, err, how = _cli_full_disk(E, d, ["shards", "pack", str(st), "{OUT}",
                                             "--resolution", "64"], "sh")
    _tb(row, err)
    row.rc, row.status, row.message = rc, how, first_line(err)
    row.check = one_line_error(rc, err, "No space left on device", "sh")
    return finish(row, st)


def case_export_careless(E: Env) -> Row:
    row = Row("export_careless", "export --overwrite onto the store / its parent / a scene "
              "folder inside it refused (store untouched); OUT under a file, on a read-only mount, on a "
              "full disk: one line naming OUT, exit 2", "clear error", fail_kind="data lost")
    d = E.tmp("export")
    st = store_copy(E, d)
    before = tree_digest(st)
    ok, notes = True, []
    for out in (st, st.parent, st / "scenes" / "sample_a"):
        rc, o, err = E.cli("export", "colmap", str(st), str(out), "--overwrite")
        _tb(row, err)
        ok = ok and one_line_error(rc, err, "store")
    ok = ok and tree_digest(st) == before
    notes.append(f"overwrite onto the store x3: {'refused' if ok else 'NOT refused'}")
    (d / "afile").write_text("x")
    rc, o, err = E.cli("export", "colmap", str(st), str(d / "afile" / "out"))
    _tb(row, err)
    ok = ok and one_line_error(rc, err, str(d / "afile"))
    notes.append(f"under a file rc={rc}")
    ro = d / "ro"
    if _mount_tmpfs(ro, "ro,size=1m"):
        try:
            rc, o, err = E.cli("export", "colmap", str(st), str(ro / "out"))
        finally:
            _umount(ro)
        _tb(row, err)
        ok = ok and one_line_error(rc, err, str(ro / "out"), "Read-only")
        notes.append(f"read-only tmpfs rc={rc}")
    else:
        notes.append("read-only mount: not permitted here, not run")
    rc, o, err, how = _cli_full_disk(E, d, ["export", "colmap", str(st), "{OUT}"], "out")
    _tb(row, err)
    ok = ok and one_line_error(rc, err, "No space left on device", "out")
    notes.append(f"full disk ({how}) rc={rc}")
    row.rc, row.status, row.message = rc, "; ".join(notes), first_line(err)
    row.check = ok
    return finish(row, st)


def case_refine_bad_args(E: Env) -> Row:
    row = Row("refine_bad_args", "refine with a bad arm, --set key, seed, scene, store, or a "
              "store without held-out views: one line each, exit 2, before any flow",
              "clear error")
    d = E.tmp("refine")
    st = store_copy(E, d)
    cases = ((["--arms", "banana"], "banana"), (["--set", "banana=1"], "banana"),
             (["--seeds", "-1"], "seeds"), (["--scenes", "nosuch"], "nosuch"), ([], "held-out"))
    ok, codes = True, []
    for extra, needle in cases:
        rc, o, err = E.cli("refine", str(st), *extra)
        _tb(row, err)
        ok = ok and one_line_error(rc, err, needle)
        codes.append(rc)
    rc, o, err = E.cli("refine", str(d / "nostore"))
    _tb(row, err)
    ok = ok and one_line_error(rc, err, str(d / "nostore"))
    row.rc, row.status, row.message = rc, f"exit codes {codes + [rc]}", first_line(err)
    row.check = ok
    return row


def case_evaluate_bad_args(E: Env) -> Row:
    row = Row("evaluate_bad_args", "evaluate --quick with an unknown knob, knob value, --set "
              "key, proc: scene, seed -1, --preset-set outside --presets, --set preset=: one "
              "line each, exit 2, nothing written", "clear error",
              fail_kind="silent wrong data")
    d = E.tmp("evaluate")
    cases = ((["--knob", "banana=1,2"], "banana"), (["--knob", "grid_r=banana"], "banana"),
             (["--set", "banana=1"], "banana"), (["proc:nosuch"], "proc:nosuch"),
             (["--seeds", "-1"], "seeds"), (["--preset-set", "paper:seed=3"], "paper"),
             (["--preset", "fast", "--set", "preset=paper"], "preset=paper"))
    ok, codes = True, []
    for extra, needle in cases:
        rc, o, err = E.cli("evaluate", "--quick", "--out", str(d / "ev"), *extra)
        _tb(row, err)
        ok = ok and one_line_error(rc, err, needle)
        codes.append(rc)
    row.rc, row.status, row.message = rc, f"exit codes {codes}", first_line(err)
    row.check = ok and not (d / "ev").exists()
    return row


def case_report_corrupt_views(E: Env) -> Row:
    row = Row("report_corrupt_views", "one scene's views.parquet garbage: the report is "
              "written with the healthy scene, the bad one marked unreadable; exit 1, one "
              "line naming the scene", "clear error")
    d = E.tmp("report")
    st = store_copy(E, d)
    bad = st / "scenes" / "sample_b" / "v0001" / "views.parquet"
    bad.write_bytes(b"garbage")
    rc, o, err = E.cli("report", str(st), "-o", str(d / "r.html"))
    _tb(row, err)
    text = (d / "r.html").read_text() if (d / "r.html").is_file() else ""
    row.rc, row.message = rc, first_line(err)
    row.check = (one_line_error(rc, err, "sample_b", code=1) and "unreadable" in text
                 and text.count("<canvas") == 1)
    return row


def case_colmap_track(E: Env) -> Row:
    row = Row("colmap_track_missing_image", "a points3D.txt track names image 999: inspect "
              "exit 2 naming the scene and points3D.txt (was an IndexError traceback)",
              "clear error")
    d = E.tmp("track")
    s = E.sample(d / "trk")
    p = s / "sparse" / "0" / "points3D.txt"
    lines = p.read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if not ln.startswith("#"))
    f = lines[k].split()
    f[8] = "999"
    lines[k] = " ".join(f)
    p.write_text("\n".join(lines) + "\n")
    rc, o, err = E.cli("inspect", str(s))
    _tb(row, err)
    row.rc, row.message = rc, first_line(err)
    row.check = one_line_error(rc, err, "'trk'", str(p), "999")
    return row


def case_sample_views_1(E: Env) -> Row:
    row = Row("sample_scene_views_1", "sample-scene --views 1: one line, exit 2, nothing "
              "written", "clear error")
    d = E.tmp("views1")
    rc, o, err = E.cli("sample-scene", str(d / "s"), "--views", "1")
    _tb(row, err)
    row.rc, row.message = rc, first_line(err)
    row.check = one_line_error(rc, err, "n_views", str(d / "s")) and not (d / "s").exists()
    return row


def case_deleted_version(E: Env) -> Row:
    row = Row("deleted_version_resume", "a scene's version folder deleted by hand: resume "
              "runs the scene again and ends ok (was: the flow failed and suggested resume)")
    d = E.tmp("deleted_version")
    s = E.sample(d / "sample")
    store = d / "store"
    E.run([s], store)
    v = store / "scenes" / "sample" / (store / "scenes" / "sample" / "CURRENT").read_text().strip()
    shutil.rmtree(v)
    rc, out, err = E.cli("resume", str(store), "--no-progress")
    _tb(row, err)
    st = status_of(store, "sample")
    row.rc, row.status, row.message = rc, st.get("status", ""), first_line(out + err)
    from freescale_core.store.store import Store

    cur = None
    try:
        cur = Store(store).current_version_dir("sample")
    except Exception as e:  # noqa: BLE001
        row.notes.append(str(e))
    row.check = rc == 0 and st.get("status") == "ok" and cur is not None and cur.is_dir()
    return finish(row, store)


def case_export_owns_bytes(E: Env) -> Row:
    row = Row("export_owns_bytes", "an exported image and the exported gaussians.ply edited "
              "in place: the published version, _work/gaussians.ply and the capture keep their "
              "bytes (was: hard links, the edit reached the capture and every version)",
              fail_kind="silent wrong data")
    from freescale_core.store.store import Store

    d = E.tmp("own_bytes")
    ref = published_store(E)  # read only: an export never writes into its store
    st = Store(ref)
    vdir = st.current_version_dir("sample_a")
    src = Path(st.read_status("sample_a")["source"])
    watched = [*sorted((vdir / "images").iterdir()), vdir / "gaussians.ply",
               ref / "scenes" / "sample_a" / "_work" / "gaussians.ply",
               *sorted((src / "images").iterdir())]
    before = {str(q): q.read_bytes() for q in watched}
    links = sum(q.stat().st_nlink > 1 for q in (vdir / "images").iterdir())
    rc1, o1, e1 = E.cli("export", "colmap", str(ref), str(d / "colmap"), "--scenes", "sample_a")
    rc2, o2, e2 = E.cli("export", "gsplat", str(ref), str(d / "gsplat"), "--scenes", "sample_a")
    _tb(row, e1, e2)
    edited = [sorted((d / "colmap" / "sample_a" / "images").iterdir())[0],
              d / "gsplat" / "sample_a" / "gaussians.ply"]
    for q in edited:
        with open(q, "r+b") as f:
            f.seek(q.stat().st_size // 2)
            f.write(b"EDITED IN PLACE")
    same = sum(q.read_bytes() == before[str(q)] for q in watched)
    row.rc, row.status = max(rc1, rc2), f"{same} of {len(watched)} files unchanged"
    row.message = (f"version images hard-linked elsewhere: {links}; "
                   f"exported files edited: {len(edited)}")
    row.check = rc1 == rc2 == 0 and same == len(watched) and links == 0
    return row


def case_lvsm_resume_other_shards(E: Env) -> Row:
    row = Row("lvsm_resume_other_shards", "train-lvsm --resume of a run on another shards "
              "folder: one line, exit 2, split.json untouched (was: accepted, the held-out "
              "scene trained on, split.json rewritten)", "clear error",
              fail_kind="silent wrong data")
    d = E.tmp("lvsm_resume")
    out = _packed(E, d)
    other = d / "other" / "sh"
    shutil.copytree(out, other)
    run = d / "run"
    tiny = ["--set", "train.batch_size=2", "--set", "train.eval_every=1", "--set",
            "train.ckpt_every=1", "--set", "train.eval_samples=2", "--set",
            'train.model_overrides={"d_model": 32, "n_layers": 1, "n_heads": 2, '
            '"image_size": 32}', "--set", "train.sampler.n_input=2", "--set",
            "train.sampler.n_target=1", "--set", "train.sampler.reference_length=null"]
    rc1, o1, e1 = E.cli("train-lvsm", str(out), "--steps", "1", "--out", str(run), *tiny)
    split0 = (run / "split.json").read_bytes() if (run / "split.json").is_file() else b""
    rc, o, err = E.cli("train-lvsm", str(other), "--steps", "1", "--out", str(run),
                       "--resume", *tiny)
    _tb(row, e1, err)
    row.rc, row.status, row.message = rc, f"first run rc={rc1}", first_line(err)
    if rc1 != 0:
        row.notes.append(f"first run: {e1[-400:]!r}")
    row.check = (rc1 == 0 and bool(split0) and one_line_error(rc, err, "cannot resume", str(other))
                 and (run / "split.json").read_bytes() == split0)
    return row


def case_symlinked_image(E: Env) -> Row:
    row = Row("symlinked_image", "3 images symbolic links to files outside the scene folder "
              "(one behind a linked folder): run ok, the version and the colmap / nerfstudio / "
              "gsplat exports hold their bytes; the targets deleted: nothing dangles (was: "
              "exported as links that dangled)", fail_kind="silent wrong data")
    d = E.tmp("symlink")
    s = E.sample(d / "sample")
    outside = d / "photos"
    (outside / "day2").mkdir(parents=True)
    imgs = sorted((s / "images").iterdir())
    want = {q.name: q.read_bytes() for q in imgs}
    for q in imgs[:2]:  # two linked files
        shutil.move(q, outside / q.name)
        os.symlink(outside / q.name, q)
    # a third behind a linked folder: the model names it day2/<name>
    moved = imgs[2].name
    shutil.move(imgs[2], outside / "day2" / moved)
    os.symlink(outside / "day2", s / "images" / "day2")
    model = s / "sparse" / "0" / "images.txt"
    model.write_text(model.read_text().replace(f" {moved}\n", f" day2/{moved}\n"))
    want[f"day2/{moved}"] = want.pop(moved)
    store = d / "store"
    rc, out, err = E.run([s], store)
    st = status_of(store, "sample")
    codes = []
    for fmt in ("colmap", "nerfstudio", "gsplat"):
        rc_e, o_e, e_e = E.cli("export", fmt, str(store), str(d / f"exp_{fmt}"))
        _tb(row, e_e)
        codes.append(rc_e)
    _tb(row, err)
    shutil.rmtree(outside)  # the photos moved away after the run
    roots = [store, *(d / f"exp_{f}" for f in ("colmap", "nerfstudio", "gsplat"))]
    links = [q for r in roots for q in r.rglob("*") if q.is_symlink()]
    from freescale_core.store.store import Store

    vdir = Store(store).current_version_dir("sample") if st.get("status") == "ok" else None
    kept = vdir is not None and all((vdir / "images" / n).read_bytes() == b
                                    for n, b in want.items())
    exported = [q for f in ("colmap", "nerfstudio", "gsplat")
                for q in (d / f"exp_{f}").rglob("*.png") if "images" in q.parts]
    readable = all(q.is_file() for q in exported)
    row.rc, row.status = rc, f"{st.get('status')}; exports rc={codes}"
    row.message = (f"links in the store and exports: {len(links)}; version images equal to "
                   f"the originals: {kept}; {len(exported)} exported images readable: {readable}")
    row.check = (rc == 0 and st.get("status") == "ok" and codes == [0, 0, 0] and not links
                 and kept and readable and len(exported) > 0)
    return finish(row, store)


def case_concurrent_runs(E: Env) -> Row:
    row = Row("concurrent_runs", "two runs on one scene, different configs (80 and 60 "
              "iterations), started 1 s apart: one publishes, the other exits 1 naming the "
              "holder of the scene; the version's config.json is the config its Gaussians "
              "were trained with (was: config of one run, gaussians.ply of the other)",
              "clear error", fail_kind="silent wrong data")
    d = E.tmp("concurrent")
    s = E.sample(d / "sample")
    store = d / "store"
    kw = dict(stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    a = E.start_run([s], store, **kw)
    time.sleep(1.0)
    b = E.start_run([s], store, "--set", "recon.max_iterations=60", "--force", **kw)
    (oa, ea), (ob, eb) = a.communicate(timeout=1800), b.communicate(timeout=1800)
    _tb(row, ea, eb)
    rcs = (a.returncode, b.returncode)
    busy = [i for i, e in enumerate((oa + ea, ob + eb)) if "being written by another run" in e]
    from freescale_core.store.store import Store

    stt = Store(store)
    st = stt.read_status("sample")
    vers = sorted(x.name for x in (store / "scenes" / "sample").glob("v0*"))
    cfg_it = trained = None
    try:
        v = json.loads((stt.current_version_dir("sample") / "config.json").read_text())
        cfg_it = v["config"]["recon"]["max_iterations"]
        trained = st.get("info", {}).get("iterations")
        same_hash = v["config_hash"] == st.get("config_hash")
    except Exception as e:  # noqa: BLE001
        row.notes.append(f"version unreadable: {e}")
        same_hash = False
    row.rc = max(rcs)
    row.status = f"exit codes {list(rcs)}; versions {vers}"
    row.message = (f"{'run ' + 'ab'[busy[0]] + ': ' if busy else ''}"
                   f"{first_line((oa + ea, ob + eb)[busy[0]]) if busy else 'no busy message'}"
                   f"; CURRENT config max_iterations={cfg_it}, trained {trained}")
    winner = 80 if rcs == (0, 1) else 60 if rcs == (1, 0) else None
    row.check = (sorted(rcs) == [0, 1] and len(busy) == 1 and rcs[busy[0]] == 1
                 and cfg_it == trained == winner and same_hash and len(vers) == 1)
    return finish(row, store)


def case_edited_same_size_mtime(E: Env) -> Row:
    import numpy as np
    from PIL import Image

    row = Row("edited_same_size_mtime", "an image rewritten with the same size and mtime: "
              "the next run re-runs the scene (not 'already complete'), its ingest key "
              "changes (was: 'already complete', --force reused every stage)",
              fail_kind="silent wrong data")
    d = E.tmp("same_size")
    s = E.sample(d / "sample")
    img = sorted((s / "images").iterdir())[0]
    a = np.asarray(Image.open(img)).copy()
    Image.fromarray(a).save(img, compress_level=0)  # uncompressed: size fixed by H, W
    store = d / "store"
    E.run([s], store)
    k0 = json.loads((store / "scenes/sample/_work/ingest.done.json").read_text())["key"]
    st0 = img.stat()
    a[:10, :10] = 255 - a[:10, :10]
    Image.fromarray(a).save(img, compress_level=0)
    os.utime(img, ns=(st0.st_atime_ns, st0.st_mtime_ns))
    st1 = img.stat()
    rc, out, err = E.run([s], store)
    k1 = json.loads((store / "scenes/sample/_work/ingest.done.json").read_text())["key"]
    row.rc, row.status = rc, status_of(store, "sample").get("status")
    row.message = (f"size {st0.st_size}->{st1.st_size}, mtime equal "
                   f"{st0.st_mtime_ns == st1.st_mtime_ns}; ingest key changed {k0 != k1}; "
                   f"{first_line(out)}")
    row.check = (rc == 0 and st0.st_size == st1.st_size and st0.st_mtime_ns == st1.st_mtime_ns
                 and k1 != k0 and "1 scenes ok, 0 already complete" in out)
    return finish(row, store)


STAGES = ("ingest", "reconstruct", "select", "freeviews")


def case_code_edit_invalidates(E: Env) -> Row:
    row = Row("code_edit_invalidates", "a comment appended to recon/bounds.py, then to "
              "freeviews/trust.py, in a copy of the code: run --force re-runs exactly the "
              "stages that import the edited module and those after them (was: 'reconstruct "
              "reused checkpoint', the free-view stage reused: two code versions mixed)",
              fail_kind="silent wrong data")
    from freescale_core.codekey import LAYERS, reached
    from tasks.scene_tasks import STAGE_ROOTS

    d = E.tmp("code_edit")
    tree = d / "code"
    for top in LAYERS:
        shutil.copytree(REPO / top, tree / top, ignore=shutil.ignore_patterns("__pycache__"))
    C = Env(E.root, E.env.get("PREFECT_API_URL"))
    C.env["PYTHONPATH"] = str(tree)
    s = E.sample(d / "sample")
    store = d / "store"

    def keys() -> dict[str, str]:
        w = store / "scenes" / "sample" / "_work"
        return {k: json.loads((w / f"{k}.done.json").read_text())["key"] for k in STAGES}

    rc, out, err = C.run([s], store, cwd=tree)
    ok, notes = rc == 0, [f"first run rc={rc}"]
    prev = keys() if rc == 0 else {}
    for mod in ("freescale_core.recon.bounds", "freescale_core.freeviews.trust"):
        f = tree / (mod.replace(".", "/") + ".py")
        f.write_text(f.read_text() + "\n# an edit that changes no behaviour\n")
        first = next(i for i, k in enumerate(STAGES) if mod in reached(STAGE_ROOTS[k]))
        expect = set(STAGES[first:])
        rc, out, err = C.run([s], store, "--force", cwd=tree)
        _tb(row, err)
        now = keys()
        changed = {k for k in STAGES if now[k] != prev.get(k)}
        prev = now
        ok = ok and rc == 0 and changed == expect
        notes.append(f"{mod.split('.', 1)[1]}: re-ran {sorted(changed, key=STAGES.index)} "
                     f"(expected {sorted(expect, key=STAGES.index)}), rc={rc}")
    row.rc, row.status, row.message = rc, "", "; ".join(notes)
    row.check = ok
    return finish(row, store)


# --------------------------------------------------------------------------- cases
def case_markup_error(E: Env) -> Row:
    """A failed scene whose error ends in [<path>]: the CLI prints the manifest and hint."""
    row = Row("error_with_path", "exit 1, failed scene named with its file; manifest and "
              "resume hint printed; scenes ls works", "clear error")
    d = E.tmp("markup")
    good = E.sample(d / "good")
    bad = E.sample(d / "bad")
    img = sorted((bad / "images").iterdir())[3]
    img.write_bytes(img.read_bytes()[:200])
    store = d / "store"
    rc, out, err = E.run([good, bad], store)
    st = status_of(store, "bad")
    rc2, out2, err2 = E.cli("scenes", "ls", str(store))
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
    from freescale_core.scene.ply import write_ply

    row = Row("far_gaussians_ply", "certainty box bounded by cameras + points; free views > 0")
    d = E.tmp("far")
    s = E.sample(d / "sample")
    g = first_run_gaussians(E, s, d / "store0")
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

    from freescale_core.scene.ply import write_ply

    row = Row("3dgs_iteration_order", "point_cloud/iteration_30000 used, not iteration_7000")
    d = E.tmp("iter")
    s = E.sample(d / "sample")
    g = first_run_gaussians(E, s, d / "store0")
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
    p = E.start_run([s], store, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for(store, "sample", "reconstruct", p, limit=600)
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


def _wait_for(store: Path, sid: str, point: str, p: subprocess.Popen, limit: float = 900
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
        p = E.start_run([s], store, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                        start_new_session=True)
        hit = _wait_for(store, "sample", point, p)
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

    from freescale_core.scene.ply import write_ply

    row = Row("ply_other_frame", "a PLY normalised like gsplat's normalize_world_space: "
              "refused with PSNR, extent ratio and the likely cause", "clear error")
    d = E.tmp("frame")
    s = E.sample(d / "sample")
    g = first_run_gaussians(E, s, d / "store0")
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
CARELESS = {
    "pack_into_store": case_pack_into_store,
    "pack_not_a_store": case_pack_not_a_store,
    "pack_scenes_twice_user_folder": case_pack_twice_and_user_folder,
    "truncated_shard_chunk": case_truncated_chunk,
    "corrupt_shard_byte_pose": case_flipped_shard,
    "pack_full_disk": case_pack_full_disk,
    "export_careless": case_export_careless,
    "refine_bad_args": case_refine_bad_args,
    "evaluate_bad_args": case_evaluate_bad_args,
    "report_corrupt_views": case_report_corrupt_views,
    "colmap_track_missing_image": case_colmap_track,
    "sample_scene_views_1": case_sample_views_1,
    "export_owns_bytes": case_export_owns_bytes,
    "lvsm_resume_other_shards": case_lvsm_resume_other_shards,
}
CASES.update(CARELESS)
CASES["deleted_version_resume"] = case_deleted_version
CASES["symlinked_image"] = case_symlinked_image
CASES["concurrent_runs"] = case_concurrent_runs
CASES["edited_same_size_mtime"] = case_edited_same_size_mtime
CASES["code_edit_invalidates"] = case_code_edit_invalidates
QUICK = ("bad_set", "missing_path", "memory_guard")  # no Prefect server, no reconstruction
# no Prefect server of the bench's own (train-lvsm starts a temporary one per command)
NO_SERVER = (*QUICK, *CARELESS)


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
    ap.add_argument("--careless", action="store_true",
                    help=f"only the careless-use cases ({', '.join(CARELESS)})")
    ap.add_argument("--cases", default="", help="comma-separated case names")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--keep", action="store_true", help="keep the temp folder")
    a = ap.parse_args(argv)
    names = [c for c in a.cases.split(",") if c] or (
        list(QUICK) if a.quick else list(CARELESS) if a.careless else list(CASES))
    bad = [n for n in names if n not in CASES]
    if bad:
        print(f"error: unknown case(s) {bad}; known: {', '.join(CASES)}", file=sys.stderr)
        return 2
    root = Path(tempfile.mkdtemp(prefix="freescale-faults-"))
    try:
        if all(n in NO_SERVER for n in names):
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
    return 0 if all(r.verdict in ("survived", "clear error") for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
