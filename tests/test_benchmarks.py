"""The benchmarks a user runs: each is ``python -m benchmarks.NAME`` from the repository root,
with no ``sys.path`` edit in the script, and the docs name them that way."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / "benchmarks"
# scripts whose owners are changing them on other branches; each still edits sys.path
NOT_YET: set[str] = set()
# documented as `python -m benchmarks.NAME`; the others' docs are changed with their scripts
CONVERTED = {"fidelity", "fixer_speed", "ingest", "loader", "masks", "rasterizer", "recon",
             "selection", "store_diff"}
MODULES = sorted(p.stem for p in BENCH.glob("*.py") if p.stem != "__init__")
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


@pytest.mark.parametrize("name", MODULES)
def test_no_sys_path_edit(name):
    if name in NOT_YET:
        pytest.skip(f"benchmarks/{name}.py is being changed on another branch")
    text = (BENCH / f"{name}.py").read_text()
    assert "sys.path" not in text, f"benchmarks/{name}.py edits sys.path"


# One interpreter for all of them (each imports torch): runpy.run_module is what ``-m`` does.
_RUN_ALL = """
import contextlib, io, runpy, sys
for name in sys.argv[1:]:
    sys.argv = [name, "--help"]
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            runpy.run_module("benchmarks." + name, run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as e:
        code = e.code
    print(name, code, out.getvalue().startswith("usage:"), flush=True)
"""


def test_each_runs_as_a_module():
    """``python -m benchmarks.NAME --help`` from the repository root, no PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    p = subprocess.run([sys.executable, "-c", _RUN_ALL, *MODULES], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    got = {line.split()[0]: line.split()[1:] for line in p.stdout.splitlines()}
    assert got == {m: ["0", "True"] for m in MODULES}, (got, p.stderr[-2000:])


def test_docs_name_the_module_form():
    """A doc that names a converted benchmark as a script path is out of date."""
    done = "|".join(sorted(CONVERTED))
    script = re.compile(rf"benchmarks/({done})\.py")
    bad = [f"{d.name}:{n}: {line.strip()}" for d in DOCS
           for n, line in enumerate(d.read_text().splitlines(), 1) if script.search(line)]
    assert not bad, "use `python -m benchmarks.NAME`:\n" + "\n".join(bad)
