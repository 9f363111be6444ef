"""Temporary files a killed writer leaves in a scene are removed by the scene's next writer
(a SIGKILL during reconstruction left ``_work/.progress.json.tmp-*`` behind)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

from freescale_core.files import HOST, clean_stale_temps, temp_name, write_json_atomic
from freescale_core.store.store import Store


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_temp_names_carry_host_and_pid(tmp_path):
    t = temp_name(tmp_path / "status.json")
    assert t.name.startswith(f".status.json.tmp-{HOST}-{os.getpid()}-")
    write_json_atomic(tmp_path / "status.json", {"a": 1})
    assert [p.name for p in tmp_path.iterdir()] == ["status.json"]


def test_the_next_writer_removes_a_dead_writers_temps_only(tmp_path):
    st = Store(tmp_path)
    work = st.scene_dir("a") / "_work"
    work.mkdir(parents=True)
    dead = work / f".progress.json.tmp-{HOST}-{_dead_pid()}-0123abcd"
    dead.write_text("{")
    dead_dir = work / f".scene.tmp-{HOST}-{_dead_pid()}-0123abcd"
    (dead_dir / "x").mkdir(parents=True)
    mine = work / f".other.json.tmp-{HOST}-{os.getpid()}-0123abcd"   # this process: live
    mine.write_text("{")
    foreign = work / ".old.json.tmp-0123abcd"                     # owner unknown, fresh
    foreign.write_text("{")
    staged = st.scene_dir("a") / f".staging-{HOST}-1-x" / f".f.tmp-{HOST}-{_dead_pid()}-1"
    staged.parent.mkdir()
    staged.write_text("")                                          # the staging rule's
    with st.scene_writer("a"):
        pass
    assert not dead.exists() and not dead_dir.exists()
    assert mine.exists() and foreign.exists() and staged.exists()
    old = time.time() - 7 * 3600
    os.utime(foreign, (old, old))
    assert clean_stale_temps(st.scene_dir("a")) == ["_work/.old.json.tmp-0123abcd"]
