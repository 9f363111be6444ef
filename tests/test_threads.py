"""The compute-thread helper: concurrent holders in threads of one process keep torch's
process-wide thread count (a per-call set/restore lets one scene reset another's setting)."""

from __future__ import annotations

import threading

import pytest
import torch

from freescale_core import threads as th
from freescale_core.threads import compute_threads, torch_lease_state


@pytest.fixture
def openblas():
    """``(get, set)`` of numpy's OpenBLAS with the process count set to 2 (skip without one)."""
    ctl = th._openblas_controls()
    if ctl is None:
        pytest.skip("numpy is not linked to an OpenBLAS this test can find")
    ctl[1](2)
    return ctl


def test_lease_survives_interleaved_exits():
    before = torch.get_num_threads()
    want = 1 if before != 1 else 2
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen: dict = {}

    def scene_a():
        with compute_threads(want):
            a_in.set()
            b_in.wait(5)
        a_out.set()

    def scene_b():
        a_in.wait(5)
        with compute_threads(want):
            b_in.set()
            a_out.wait(5)
            seen["b_after_a_left"] = torch.get_num_threads()  # A has left: still B's setting
            seen["holders"] = torch_lease_state()["holders"]

    ts = [threading.Thread(target=scene_a), threading.Thread(target=scene_b)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(10)
    assert seen == {"b_after_a_left": want, "holders": 1}
    assert torch.get_num_threads() == before
    assert torch_lease_state() == {"holders": 0, "active": None, "saved": None}


def test_first_setting_wins_and_numba_is_per_thread():
    import numba

    before = torch.get_num_threads()
    nb = numba.get_num_threads()
    with compute_threads(1, 1) as g1:
        assert torch.get_num_threads() == 1 and numba.get_num_threads() == 1
        assert g1 == {"torch": 1, "numba": 1}
        with compute_threads(2) as g2:
            assert g2["torch"] == 1 and torch.get_num_threads() == 1
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before and numba.get_num_threads() == nb


def test_no_set_num_threads_outside_the_helper():
    """Only freescale_core/threads.py sets torch's process-wide thread count."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    bad = [str(p.relative_to(root)) for sub in ("freescale_core", "tasks", "flows")
           for p in (root / sub).rglob("*.py")
           if "torch.set_num_threads" in p.read_text() and p.name != "threads.py"]
    assert bad == []


def test_blas_lease_survives_interleaved_exits(openblas):
    """OpenBLAS's count is process-wide and its float32 products depend on it: scene B's GEMMs
    keep the selection's setting after scene A (which set it first) leaves."""
    ctl = openblas
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen: dict = {}

    def scene_a():
        with th.blas_threads(1):
            a_in.set()
            b_in.wait(5)
        a_out.set()

    def scene_b():
        a_in.wait(5)
        with th.blas_threads(1):
            b_in.set()
            a_out.wait(5)
            seen["b_after_a_left"] = int(ctl[0]())  # the old set/restore gave 2 here

    ts = [threading.Thread(target=scene_a), threading.Thread(target=scene_b)]
    for t in ts:
        t.start()
    for t in ts:
        t.join(10)
    assert seen == {"b_after_a_left": 1}
    assert int(ctl[0]()) == 2 and th._BLAS_LEASE.state()["holders"] == 0


def test_blas_controls_lookup_is_seen_by_concurrent_first_callers(monkeypatch):
    """Two scenes starting their selection together both find OpenBLAS's controls: a caller
    arriving while the first lookup is still scanning waits for it instead of getting None
    (None meant no lease: that scene's GEMMs ran at 2 threads and its nms_overlap differed)."""
    import time

    found = ("get", "set")

    def slow_find():
        time.sleep(0.2)
        return found

    monkeypatch.setattr(th, "_BLAS", None)
    monkeypatch.setattr(th, "_find_openblas", slow_find)
    seen = []
    ts = [threading.Thread(target=lambda: seen.append(th._openblas_controls())) for _ in range(3)]
    for t in ts:
        t.start()
        time.sleep(0.02)
    for t in ts:
        t.join()
    assert seen == [found] * 3


def test_a_second_scenes_stage_leaves_a_running_selection_at_its_blas_count(monkeypatch, openblas):
    """Thread runner: scene A's selection holds OpenBLAS at 1 thread while scene B's stage
    starts and ends. The stage used threadpoolctl's set/restore and switched A's GEMMs to
    2 threads mid-selection (fresh-clone CI, stop 30: sample_a's nms_overlap off by float32
    ulps against the resumed / Dask stores); through the lease the first holder's count stays."""
    from tasks import stage

    ctl = openblas
    monkeypatch.setattr(stage, "BLAS_THREADS", 2)  # a count other than the selection's
    b_in, b_go = threading.Event(), threading.Event()
    seen: dict = {}

    def scene_b_stage():
        with stage.stage_blas_threads():
            b_in.set()
            b_go.wait(5)

    with th.blas_threads(1):
        t = threading.Thread(target=scene_b_stage)
        t.start()
        b_in.wait(5)
        seen["while_b_runs"] = int(ctl[0]())
        b_go.set()
        t.join(10)
        seen["after_b_left"] = int(ctl[0]())
    assert seen == {"while_b_runs": 1, "after_b_left": 1}
    assert int(ctl[0]()) == 2 and th._BLAS_LEASE.state()["holders"] == 0
