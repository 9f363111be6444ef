"""The quick subset of benchmarks/faults.py: every row survives or errors clearly."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_faults_quick_subset(capsys):
    spec = importlib.util.spec_from_file_location("faults_bench", REPO / "benchmarks" / "faults.py")
    faults = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("faults_bench", faults)  # dataclasses look their module up
    spec.loader.exec_module(faults)
    rc = faults.main(["--quick"])
    out = capsys.readouterr().out
    assert rc == 0, out
    rows = [ln for ln in out.splitlines() if ln.startswith("| ") and "verdict" not in ln]
    assert len(rows) == len(faults.QUICK)
    assert all("**clear error**" in r or "**survived**" in r for r in rows), out
