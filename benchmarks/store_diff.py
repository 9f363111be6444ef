"""Compare the published outputs of two stores scene by scene.

    python -m benchmarks.store_diff STORE_A STORE_B

For every scene in either store: views.parquet and view_graph.parquet equal (every column,
NaN == NaN), and every array in arrays.zarr equal (shape, dtype, values). Prints one row per
scene and exits 1 when any scene differs or is missing on one side. Used to show that a
refactor changed no output.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import zarr


def _arrays(group, prefix=""):
    out = {}
    for name, node in group.members():
        key = f"{prefix}{name}"
        if isinstance(node, zarr.Group):
            out.update(_arrays(node, key + "/"))
        else:
            out[key] = node[...]
    return out


def _tables_equal(a: Path, b: Path) -> str:
    ta, tb = pq.read_table(a), pq.read_table(b)
    if ta.column_names != tb.column_names:
        return f"columns differ: {sorted(set(ta.column_names) ^ set(tb.column_names))}"
    if ta.num_rows != tb.num_rows:
        return f"rows {ta.num_rows} != {tb.num_rows}"
    for c in ta.column_names:
        x, y = ta[c].to_pylist(), tb[c].to_pylist()
        try:
            ok = np.array_equal(np.asarray(x, dtype=object).astype(float),
                                np.asarray(y, dtype=object).astype(float), equal_nan=True)
        except (TypeError, ValueError):
            ok = x == y
        if not ok:
            return f"column {c} differs"
    return ""


def compare_scene(va: Path, vb: Path) -> str:
    for name in ("views.parquet", "view_graph.parquet"):
        msg = _tables_equal(va / name, vb / name)
        if msg:
            return f"{name}: {msg}"
    aa = _arrays(zarr.open_group(str(va / "arrays.zarr"), mode="r"))
    ab = _arrays(zarr.open_group(str(vb / "arrays.zarr"), mode="r"))
    if aa.keys() != ab.keys():
        return f"arrays differ: {sorted(set(aa) ^ set(ab))}"
    for k in aa:
        if aa[k].shape != ab[k].shape or aa[k].dtype != ab[k].dtype or not np.array_equal(
                aa[k], ab[k], equal_nan=aa[k].dtype.kind == "f"):
            return f"array {k} differs"
    return ""


def current(store: Path, sid: str) -> Path | None:
    cur = store / "scenes" / sid / "CURRENT"
    return store / "scenes" / sid / cur.read_text().strip() if cur.is_file() else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("store_a", type=Path)
    ap.add_argument("store_b", type=Path)
    args = ap.parse_args(argv)
    a, b = args.store_a, args.store_b
    for s in (a, b):
        if not (s / "scenes").is_dir():
            print(f"store_diff: {s}: not a store (no scenes/ folder)", file=sys.stderr)
            return 2
    ids = sorted({p.name for s in (a, b) for p in (s / "scenes").iterdir() if p.is_dir()})
    bad = 0
    print(f"{'scene':<24} {'views':>6} {'free':>5}  result")
    for sid in ids:
        va, vb = current(a, sid), current(b, sid)
        if va is None or vb is None:
            print(f"{sid:<24} {'':>6} {'':>5}  MISSING in {'A' if va is None else 'B'}")
            bad += 1
            continue
        msg = compare_scene(va, vb)
        t = pq.read_table(va / "views.parquet", columns=["disposition"])["disposition"].to_pylist()
        print(f"{sid:<24} {len(t):>6} {t.count('free_view'):>5}  {msg or 'identical'}")
        bad += bool(msg)
    print(f"{len(ids) - bad} of {len(ids)} scenes identical")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
