"""Step-level progress: the throttled progress file, what the CLI prints from it, and which
failures are retried."""

from __future__ import annotations

import io
import json

from hypothesis import given, settings
from hypothesis import strategies as st

from freescale_core.errors import FreeScaleError, SceneError
from freescale_core.store.progress import ProgressFile, read_progress
from tasks.progress import StageReporter, describe, recon_progress
from tasks.retry import is_transient


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(0.0, 3.0), min_size=1, max_size=40), st.floats(0.5, 5.0))
def test_progress_file_is_throttled_and_always_complete(tmp_path_factory, gaps, every):
    path = tmp_path_factory.mktemp("p") / "progress.json"
    clock = Clock()
    pf = ProgressFile(path, "reconstruct", total=len(gaps), unit="steps", every=every,
                      clock=clock)
    writes, last = [], None
    for i, g in enumerate(gaps, 1):
        clock.t += g
        if pf.update(i, loss_ema=0.1):
            writes.append(clock.t)
        rec = read_progress(path)
        assert rec is not None and rec["stage"] == "reconstruct" and rec["done"] <= i
        last = rec
    # first update always written; then never two writes closer than `every`
    assert writes[0] == 1000.0 + gaps[0]
    assert all(b - a >= every - 1e-9 for a, b in zip(writes, writes[1:]))
    assert pf.update(len(gaps), force=True)
    assert read_progress(path)["done"] == len(gaps) and last["total"] == len(gaps)


def test_eta_is_linear_in_done():
    clock = Clock()
    pf = ProgressFile("/nonexistent/dir/progress.json", "x", total=100, clock=clock)
    clock.t += 10
    pf.update(25)  # write fails (no folder): progress never fails the stage
    assert pf.record["eta_s"] == 30.0


def test_reporter_and_recon_callback(tmp_path):
    from schemas.recon import ReconConfig

    cfg = ReconConfig.fast()
    rep, cb = recon_progress(str(tmp_path), "s", cfg)
    cb(10, {"n_gaussians": 3000, "loss_ema": 0.2, "phase": "grow"})
    cb(20, {"n_gaussians": 3500, "loss_ema": 0.15, "phase": "grow"})
    cb(300, {"n_gaussians": 5000, "loss_ema": 0.1, "phase": "done"})
    rec = read_progress(tmp_path / "scenes" / "s" / "_work" / "progress.json")
    assert rec["stage"] == "reconstruct" and rec["done"] == rec["total"] == 300
    assert rec["info"]["n_gaussians"] == 5000 and rec["eta_s"] == 0.0
    line = describe(rec)
    assert line.startswith("reconstruct 300/300 steps (100%)") and "5,000 Gaussians" in line
    r2 = StageReporter(str(tmp_path), "s", "freeviews", 4, "views")
    r2(1, 4, phase="render+filter", passed=1)
    assert "1/4 views (25%)" in describe(read_progress(r2.file.path))


def test_plain_progress_lines_when_piped(tmp_path):
    """Not a terminal: one plain line per running scene every few seconds, one per finish."""
    import time

    from flows.progress_view import ProgressView
    from freescale_core.store.store import Store

    stt = Store(tmp_path)
    stt.update_status("a", status="running", stage="reconstruct")
    pf = ProgressFile(stt.work_dir("a", create=True) / "progress.json", "reconstruct", 100,
                      "steps")
    pf.update(40, n_gaussians=1234)
    buf = io.StringIO()
    with ProgressView(str(tmp_path), ["a"], tty=False, every=0.2, stream=buf):
        time.sleep(0.8)
        stt.update_status("a", status="ok", counts={"n_free_views": 7})
        time.sleep(0.8)
    out = buf.getvalue().splitlines()
    assert any("a: reconstruct 40/100 steps (40%), 1,234 Gaussians" in ln for ln in out), out
    assert any("a: ok (7 free views) [1/1 scenes]" in ln for ln in out), out
    assert not any("\x1b[" in ln for ln in out)  # no terminal escapes in a log


def test_only_transient_failures_are_retried():
    class KilledWorker(Exception):
        pass

    assert is_transient(KilledWorker())
    assert is_transient(ConnectionResetError())
    assert is_transient(OSError(5, "EIO"))
    for e in (SceneError("s", "bad image", "a.png"), FreeScaleError("x"), ValueError("x"), TypeError(),
              FileNotFoundError("a.png"), KeyboardInterrupt(), None):
        assert not is_transient(e), e


def test_tasks_are_named_by_scene_and_retry_transient_only():
    from tasks import scene_tasks as t
    from tasks.retry import retry_condition

    for task, name in ((t.ingest, "ingest[{scene_id}]"),
                       (t.reconstruct, "reconstruct[{ingest_ref.scene_id}]"),
                       (t.publish, "publish[{ingest_ref.scene_id}]")):
        assert task.task_run_name == name
        assert task.retries >= 1 and task.retry_condition_fn is retry_condition
    assert "reconstruct[{ingest_ref.scene_id}]".format(
        ingest_ref=type("R", (), {"scene_id": "kermit"})) == "reconstruct[kermit]"
    json.dumps({"ok": True})
