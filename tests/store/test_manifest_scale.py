"""The manifest and the scene listing at many scenes: the fast path (one ``os.scandir`` pass,
string paths, plain file reads) gives exactly the table the per-scene ``pathlib`` path gave."""

from __future__ import annotations

import json
from pathlib import Path

import pyarrow as pa

from freescale_core.store.store import (MANIFEST_FIRST, MANIFEST_FLOAT, Store, _manifest_row,
                                        _to_arrow_column)


def _slow_manifest(root: Path) -> pa.Table:
    """The manifest as it was compiled before (stop 66): pathlib per scene, list-scan keys."""
    d = root / "scenes"
    ids = sorted(p.name for p in d.iterdir() if (p / "status.json").is_file())
    rows = [_manifest_row(json.loads((d / s / "status.json").read_text())) for s in ids]
    keys = list(MANIFEST_FIRST)
    for r in rows:
        for k in r:
            if k not in keys:
                keys.append(k)
    keys += [k for k in MANIFEST_FLOAT if k not in keys]
    cols = {}
    for k in keys:
        vals = [r.get(k) for r in rows]
        cols[k] = (pa.array([None if v in (None, "") else float(v) for v in vals], pa.float64())
                   if k in MANIFEST_FLOAT else _to_arrow_column(vals))
    return pa.table(cols)


def _varied_store(root: Path) -> Store:
    st = Store(root)
    for i in range(40):
        st.update_status(f"s{i:03d}", status=("ok", "failed", "running")[i % 3],
                         counts={f"n_c{i % 5}": i, "images": i}, seconds={"ingest": i / 7},
                         info={"scarce": bool(i % 2), "reasons": ["a", i] if i % 4 else {},
                               **({"recon_test_psnr": 20.0 + i} if i % 6 else {})},
                         error="" if i % 3 != 1 else f"scene 's{i:03d}': boom")
    (root / "scenes" / "not_a_scene").mkdir()          # no status.json: not listed
    (root / "scenes" / "stray.txt").write_text("x")    # a file in scenes/: not listed
    (root / "scenes" / "dir_status" / "status.json").mkdir(parents=True)  # not a file
    return st


def test_manifest_equals_the_slow_path(tmp_path):
    st = _varied_store(tmp_path)
    assert st.scene_ids() == [f"s{i:03d}" for i in range(40)]
    fast = st.manifest()
    assert fast.equals(_slow_manifest(tmp_path), check_metadata=False)
    assert fast.schema == _slow_manifest(tmp_path).schema
    assert not st.manifest_stale()
    st.update_status("s007", status="ok", counts={"n_new": 1})
    assert st.manifest_stale()
    assert st.manifest().equals(_slow_manifest(tmp_path))


def test_read_only_store_compiles_the_same_table_in_memory(tmp_path, monkeypatch):
    st = _varied_store(tmp_path)

    def refuse(self):
        raise PermissionError("read-only")

    monkeypatch.setattr(Store, "compile_manifest", refuse)
    assert st.manifest().equals(_slow_manifest(tmp_path))
    assert not st.manifest_path.exists()
