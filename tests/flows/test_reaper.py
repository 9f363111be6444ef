"""Prefect's temporary server dies with the CLI that started it, even after SIGKILL
(issue 12: every SIGKILL of a run left the ~220 MB server running)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from flows.reaper import SERVER_MARK, _alive, _is_server, reap

REPO = Path(__file__).resolve().parents[2]


def _sleeper(*extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", *extra])


def test_reap_stops_the_server_once_its_starter_is_killed():
    starter, server = _sleeper(), _sleeper(SERVER_MARK)
    try:
        # the reaper starts after the server is launched; here, wait until the child shows
        # its command line (on a loaded machine the test once reaped before it did: 0 == 1)
        t0 = time.monotonic()
        while not _is_server(server.pid) and time.monotonic() - t0 < 10:
            time.sleep(0.02)
        starter.kill()
        starter.wait()
        assert reap(starter.pid, server.pid, poll=0.05) == 1
        server.wait(timeout=10)
        assert not _alive(server.pid)
    finally:
        for p in (starter, server):
            p.kill()
            p.wait()


def test_reap_leaves_a_pid_that_is_not_a_prefect_server():
    starter, other = _sleeper(), _sleeper()
    try:
        starter.kill()
        starter.wait()
        assert reap(starter.pid, other.pid, poll=0.05) == 0
        assert other.poll() is None  # still running: pid reuse is not a licence to kill
    finally:
        for p in (starter, other):
            p.kill()
            p.wait()


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if int((d / "stat").read_text().rsplit(")", 1)[1].split()[1]) == pid:
                    out.append(int(d.name))
            except (OSError, IndexError, ValueError):
                pass
    return out


def _cmdline(pid: int) -> str:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().decode(errors="replace")
    except OSError:
        return ""


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs Linux /proc")
def test_sigkill_of_the_cli_stops_its_temporary_server(tmp_path):
    """The real thing: `freescale run` without PREFECT_API_URL starts the temporary server;
    SIGKILL the CLI (only the CLI, not its group) and the server is gone within 30 s."""
    from freescale_core.scene.sample import write_sample_scene

    scene = write_sample_scene(tmp_path / "s", n_views=6, width=48, height=36, seed=0,
                               n_points=200)
    env = {k: v for k, v in os.environ.items() if k != "PREFECT_API_URL"}
    env |= {"PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PREFECT_HOME": str(tmp_path / "ph")}
    cli = subprocess.Popen([sys.executable, "-m", "flows.cli", "run", str(scene), "--store",
                            str(tmp_path / "store"), "--preset", "fast", "--no-progress",
                            "--set", "recon.max_iterations=3000", "--set",
                            "recon.min_iterations=3000"],
                           cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                           stderr=subprocess.DEVNULL, start_new_session=True)
    server = None
    try:
        t0 = time.monotonic()
        while server is None and cli.poll() is None and time.monotonic() - t0 < 240:
            server = next((c for c in _children(cli.pid) if SERVER_MARK in _cmdline(c)), None)
            time.sleep(0.2)
        assert server is not None, "the CLI never started a temporary server"
        time.sleep(1.0)  # the reaper is launched right after the server's start returns
        os.kill(cli.pid, signal.SIGKILL)
        cli.wait()
        t0 = time.monotonic()
        while _alive(server) and time.monotonic() - t0 < 30:
            time.sleep(0.2)
        assert not _alive(server), "the temporary server outlived the killed CLI"
    finally:
        if cli.poll() is None:
            cli.kill()
        if server is not None and _alive(server) and SERVER_MARK in _cmdline(server):
            os.kill(server, signal.SIGKILL)
