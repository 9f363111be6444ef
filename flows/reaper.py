"""Stop Prefect's temporary server when the process that started it dies, even by SIGKILL.

Without ``PREFECT_API_URL`` a flow run starts a temporary API server (a uvicorn child process).
The CLI's exit handlers stop it on a normal exit, Ctrl-C and SIGTERM, but a SIGKILL runs no
handler and the server (~220 MB) kept running. :func:`install` makes every temporary server
this process starts come with a *reaper*: a small process in its own session that polls the
starter's pid and, once it is gone, terminates the server (after checking that the pid still
belongs to a Prefect server: pids are reused). The reaper exits as soon as the server is gone.

    python -m flows.reaper STARTER_PID SERVER_PID     # what install() launches
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

SERVER_MARK = "prefect.server.api.server:create_app"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie (killed, not yet reaped) counts as gone
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True


def _is_server(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return SERVER_MARK.encode() in fh.read()
    except OSError:
        return False


def reap(starter: int, server: int, poll: float = 0.5, grace: float = 5.0) -> int:
    """Wait while both live; when the starter is gone, SIGTERM (then SIGKILL after ``grace``
    seconds) the server if it is still a Prefect server. Returns 1 if it stopped one."""
    while _alive(server):
        if not _alive(starter):
            if not _is_server(server):
                return 0
            os.kill(server, signal.SIGTERM)
            t0 = time.monotonic()
            while _alive(server) and time.monotonic() - t0 < grace:
                time.sleep(0.1)
            if _alive(server) and _is_server(server):
                os.kill(server, signal.SIGKILL)
            return 1
        time.sleep(poll)
    return 0


def install() -> bool:
    """Give each temporary Prefect server this process starts a reaper (idempotent).
    Returns False when this Prefect has no ``SubprocessASGIServer`` to wrap."""
    try:
        from prefect.server.api.server import SubprocessASGIServer
    except ImportError:  # pragma: no cover - another Prefect layout
        return False
    if getattr(SubprocessASGIServer, "_freescale_reaper", False):
        return True
    # the method that launches the uvicorn child (called again when a port was taken): the
    # reaper starts right after it, not after the server answers (that can take a minute)
    name = ("_run_uvicorn_command" if hasattr(SubprocessASGIServer, "_run_uvicorn_command")
            else "start")
    launch = getattr(SubprocessASGIServer, name)

    def launch_with_reaper(self, *args, **kwargs):
        out = launch(self, *args, **kwargs)
        proc = out if isinstance(out, subprocess.Popen) else getattr(self, "server_process", None)
        if proc is not None and proc.pid != getattr(self, "_freescale_reaped_pid", None):
            self._freescale_reaped_pid = proc.pid
            self._freescale_reaper_proc = subprocess.Popen(  # kept: no "still running" warning
                [sys.executable, "-m", "flows.reaper", str(os.getpid()), str(proc.pid)],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                start_new_session=True, cwd=os.path.dirname(os.path.dirname(__file__)))
        return out

    setattr(SubprocessASGIServer, name, launch_with_reaper)
    SubprocessASGIServer._freescale_reaper = True
    return True

if __name__ == "__main__":
    sys.exit(reap(int(sys.argv[1]), int(sys.argv[2])))
