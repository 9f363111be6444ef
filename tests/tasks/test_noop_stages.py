"""The orchestration benchmark's no-op mode (``FREESCALE_NOOP_STAGES=1``, tasks/stage.py):
no stage work runs, and its checkpoints never stand in for a real run's."""

from __future__ import annotations

from pathlib import Path

import tasks.stage as S


def test_noop_skips_the_work_and_never_matches_a_real_checkpoint(tmp_path, monkeypatch):
    calls = []

    def compute(work: Path):
        calls.append(work)
        (work / "out.bin").write_bytes(b"x")
        return ["out.bin"], {"n_things": 3}

    store = str(tmp_path / "store")
    monkeypatch.setattr(S, "NOOP_STAGES", True)
    ref = S.run_stage(store, "a", "ingest", {"k": 1}, [], ("freescale_core.files",), 0, compute)
    assert calls == [] and ref.key.startswith("noop-") and ref.result == {}
    monkeypatch.setattr(S, "NOOP_STAGES", False)
    real = S.run_stage(store, "a", "ingest", {"k": 1}, [], ("freescale_core.files",), 0, compute)
    assert len(calls) == 1 and real.result == {"n_things": 3}  # recomputed, not reused
    assert real.key == ref.key[len("noop-"):]
