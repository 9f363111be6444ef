"""``freescale report``: one self-contained HTML file; rendered in headless Chromium, the page
is not blank and logs no console error."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path
import numpy as np
import pytest

from freescale_core.select.run import run_selection
from freescale_core.store.layout import write_scene_outputs
from freescale_core.store.store import Store
from schemas.select import SelectConfig
from tests.select.test_select import _room
from tests.store.test_figures import fake_scene

CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser")
                 if Path(p).is_file()), None)


def make_two_scene_store(root: Path) -> Store:
    """A store with one published scene (``room``) and one failed scene (``broken``)."""
    st = Store(root)
    g, cams = _room(n=6000, n_cams=12)
    sel = run_selection(g, cams, SelectConfig.fast(), seed=1, scene_id="room")
    scene = fake_scene(cams, Path(root) / "_inputs")
    with st.publish("room") as out:
        counts = write_scene_outputs(out, scene, sel, None, out / "none.ply")
    st.update_status("room", status="ok", stage="done", counts={**sel.counts, **counts},
                     version=st.current_version_dir("room").name)
    st.update_status("broken", status="failed", stage="ingest",
                     error="[ingest] scene 'broken': image images/0003.png is truncated "
                           "<script>alert(1)</script>", error_type="CorruptImageError")
    return st


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    from flows.report import write_report

    root = tmp_path_factory.mktemp("store")
    st = make_two_scene_store(root)
    return st, write_report(st, root / "report.html")


def test_report_is_self_contained(report):
    st, path = report
    text = path.read_text()
    # both scenes, the failed one with its error (escaped: no injected script)
    assert "room" in text and "broken" in text and "CorruptImageError" in text
    assert "images/0003.png is truncated" in text
    assert "<script>alert(1)</script>" not in text
    # every figure of the published version, inline
    figs = re.findall(r'src="data:image/png;base64,', text)
    assert len(figs) == 4  # funnel, cameras, scores, certainty (no free-view stage: no sheet)
    # nothing fetched from anywhere: no http(s) src/href, no external script
    assert not re.search(r'(src|href)="(https?:)?//', text)
    # the 3D view's data: one canvas, cameras with centres and directions
    assert text.count("<canvas") == 1 and '"box": [[' in text and '"c": [[' in text


def test_cli_report(tmp_path):
    from flows.cli import main

    st = make_two_scene_store(tmp_path / "s")
    assert main(["report", str(st.root), "-o", str(tmp_path / "r.html")]) == 0
    assert (tmp_path / "r.html").stat().st_size > 50_000
    assert main(["report", str(tmp_path / "empty")]) == 2


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install chromium)")
def test_report_renders_in_headless_chromium(report, tmp_path):
    from PIL import Image

    _, path = report
    shot = tmp_path / "report.png"
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
           "--no-first-run", "--disable-background-networking", "--disable-component-update",
           "--disable-sync", "--disable-dev-shm-usage", f"--user-data-dir={tmp_path / 'ud'}",
           "--enable-logging=stderr", "--v=0", "--hide-scrollbars",
           f"--screenshot={shot}", "--window-size=1280,2400", "--virtual-time-budget=3000",
           path.as_uri()]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert shot.is_file(), p.stderr[-2000:]
    console = [ln for ln in p.stderr.splitlines()
               if "Uncaught" in ln or "ERROR:CONSOLE" in ln or ":CONSOLE(" in ln]
    assert not console, console
    im = np.asarray(Image.open(shot).convert("RGB"), np.float32)
    assert im.shape[0] >= 2000 and im.shape[1] >= 1200
    # not blank: many distinct colours, and the canvas drew the cameras (dark pixels)
    assert im.std() > 20
    assert len(np.unique(im.reshape(-1, 3)[::7], axis=0)) > 500
    keep = Path(__file__).resolve().parents[2] / "docs" / "img"
    if keep.is_dir() and shutil.which("true") and "FREESCALE_SAVE_SHOTS" in __import__("os").environ:
        shutil.copy(shot, keep / "report.png")


def test_report_with_one_corrupt_views_parquet_flags_it_and_shows_the_others(tmp_path, capsys):
    """A damaged views.parquet of one scene: the report is written with every other scene in
    full and the damaged one marked 'unreadable' naming its folder; exit 1, one error line
    naming the scene (was: a traceback and no report at all)."""
    from flows.cli import main

    st = make_two_scene_store(tmp_path / "s")
    shutil.copytree(st.root / "scenes" / "room", st.root / "scenes" / "room2")
    (st.root / "scenes" / "room2" / "status.json").unlink()
    r = st.read_status("room")
    st.update_status("room2", status="ok", stage="done", counts=r["counts"], version=r["version"])
    bad = st.current_version_dir("room2") / "views.parquet"
    bad.write_bytes(b"garbage")
    out = tmp_path / "r.html"
    assert main(["report", str(st.root), "-o", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "scene 'room2'" in err[0] and str(bad.parent) in err[0]
    text = out.read_text()
    assert "unreadable" in text and text.count("<canvas") == 1  # room's 3D view kept
