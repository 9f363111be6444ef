"""`make serve`: local Prefect server + served deployments; a deployment run; SIGTERM stops all."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_serve_run_deployment_and_sigterm(tmp_path):
    from flows.serve import wait_healthy

    port = free_port()
    env = dict(os.environ, PREFECT_PORT=str(port), PREFECT_HOME=str(tmp_path / "prefect"),
               PREFECT_SERVER_ANALYTICS_ENABLED="false")
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.Popen([sys.executable, "-m", "flows.serve"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)
    try:
        wait_healthy(f"http://127.0.0.1:{port}/api/health", timeout=120, proc=proc)
        cli_env = dict(env, PREFECT_API_URL=f"http://127.0.0.1:{port}/api")
        deadline = time.monotonic() + 90
        out = ""
        while time.monotonic() < deadline and "generate-dataset/local" not in out:
            out = subprocess.run([str(BIN / "prefect"), "deployment", "ls"], env=cli_env,
                                 capture_output=True, text=True).stdout
            time.sleep(1)
        assert "generate-dataset/local" in out
        run = subprocess.run(
            [str(BIN / "prefect"), "deployment", "run", "generate-dataset/local",
             "-p", "scenes=[]", "-p", f"store={tmp_path / 'store'}", "-p", 'config={"preset": "fast"}',
             "--watch", "--watch-timeout", "120"],
            env=cli_env, capture_output=True, text=True, timeout=180)
        assert "Completed" in run.stdout + run.stderr, run.stdout[-2000:] + run.stderr[-2000:]
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0
    # nothing is left listening on the port
    with socket.socket() as s:
        assert s.connect_ex(("127.0.0.1", port)) != 0
