"""``freescale report STORE``: one self-contained HTML report of a store."""

from __future__ import annotations

import sys
import time
from pathlib import Path


def add_parsers(sub) -> None:
    s = sub.add_parser("report", help="one self-contained HTML report of a store "
                       "(figures, a table per scene, failed scenes, a 3D camera view)")
    s.add_argument("store")
    s.add_argument("-o", "--output", default=None, help="HTML file (None: STORE/report.html)")
    s.set_defaults(fn=cmd_report)


def cmd_report(a) -> int:
    from flows.report import write_report

    from freescale_core.store.store import Store

    st = Store(a.store)
    if not st.scene_ids():
        print(f"error: no scenes in {a.store} (no scenes/*/status.json)", file=sys.stderr)
        return 2
    remote = a.output is None and "://" in a.store  # written locally, then put beside it
    out = Path(a.output or (st.root if remote else Path(a.store)) / "report.html")
    t0 = time.perf_counter()
    problems: list[str] = []
    try:
        write_report(st, out, problems)
    except OSError as e:
        print(f"error: report {out} cannot be written: {e.strerror or e}", file=sys.stderr)
        return 2
    if remote:
        st.write_file("report.html", out.read_bytes())
        print(f"report put to {st.url}/report.html")
    print(f"report written to {out} ({out.stat().st_size / 1e6:.1f} MB, "
          f"{len(st.scene_ids())} scenes) in {time.perf_counter() - t0:.1f} s")
    for p in problems:  # the report shows them as 'unreadable', the healthy scenes in full
        print(f"error: {p}", file=sys.stderr)
    return 1 if problems else 0
