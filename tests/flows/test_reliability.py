"""Issue 12: bad input, crashes and real-tool captures: every case a correct result or a clear
error, nothing lost. Quick CLI / flow cases; the full set is ``benchmarks/faults.py``."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

os.environ["PREFECT_SERVER_ANALYTICS_ENABLED"] = "false"


def _failed_store(root: Path) -> Path:
    from freescale_core.store.store import Store

    st = Store(root)
    st.update_status("bad_scene", status="failed", stage="ingest",
                     error="[ingest] scene 'bad_scene': image cannot be decoded [/data/x/[b]/img.png]",
                     error_type="CorruptImageError")
    st.update_status("good", status="ok", counts={"n_free_views": 3})
    return root


def test_cli_prints_errors_ending_in_a_bracketed_path(tmp_path, capsys):
    """An error ends in ``[<path>]``: rich must print it as text, not parse it as a tag."""
    from flows.cli import main

    store = _failed_store(tmp_path / "store")
    assert main(["shards", "ls", str(store)]) == 0
    out = capsys.readouterr().out
    assert "bad_scene" in out and "/data/x/" in out and "img.png" in out
    assert "[b]" in out  # shown literally, not eaten as markup


def test_print_manifest_survives_markup_in_every_cell(tmp_path, capsys):
    from flows.cli import _print_manifest
    from freescale_core.store.store import Store

    st = Store(tmp_path / "[s]")
    st.update_status("[x]", status="failed", error="[/bold] [red]x[/red] [/a/b]")
    _print_manifest(st)
    out = capsys.readouterr().out
    assert "[/bold]" in out and "[/a/b]" in out
