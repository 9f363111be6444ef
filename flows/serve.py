"""``make serve``: a local Prefect server (SQLite, 127.0.0.1) plus the served deployments.

Both run in the foreground as child processes; SIGTERM or Ctrl-C stops both cleanly. Then,
from another shell::

    export PREFECT_API_URL=http://127.0.0.1:4200/api
    prefect deployment run 'generate-dataset/local' -p 'scenes=["data/sample-scene"]' -p store=data/store -p 'config={"preset": "fast"}'
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import urllib.request


def wait_healthy(url: str, timeout: float = 90.0, proc: subprocess.Popen | None = None) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"Prefect server exited with code {proc.returncode}")
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        time.sleep(0.5)
    raise TimeoutError(f"Prefect server not healthy at {url} after {timeout:.0f} s")


def server_env(port: int) -> dict:
    env = os.environ.copy()
    env["PREFECT_API_URL"] = f"http://127.0.0.1:{port}/api"
    env["PREFECT_SERVER_API_HOST"] = "127.0.0.1"
    env["PREFECT_SERVER_API_PORT"] = str(port)
    env.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    env.setdefault("DO_NOT_TRACK", "1")
    env.setdefault("PREFECT_HOME", os.path.abspath(".prefect"))
    return env


def main(port: int = 4200) -> int:
    env = server_env(port)
    procs: list[subprocess.Popen] = []

    def stop(*_):
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()

    def on_signal(signum, _frame):
        stop()
        sys.exit(0)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        server = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start",
                                   "--host", "127.0.0.1", "--port", str(port)], env=env)
        procs.append(server)
        wait_healthy(f"http://127.0.0.1:{port}/api/health", proc=server)
        print(f"Prefect server: http://127.0.0.1:{port}  (UI and API; SQLite in {env['PREFECT_HOME']})",
              flush=True)
        served = subprocess.Popen([sys.executable, "-m", "flows.deployments"], env=env)
        procs.append(served)
        while all(p.poll() is None for p in procs):
            time.sleep(0.5)
        return max(p.returncode or 0 for p in procs if p.poll() is not None)
    finally:
        stop()


if __name__ == "__main__":
    sys.exit(main(int(os.environ.get("PREFECT_PORT", 4200))))
