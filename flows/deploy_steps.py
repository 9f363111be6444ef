"""Deployment steps of ``prefect.yaml`` (run by a worker before the flow is loaded).

``enter_project`` makes the flow run's working directory the project folder, wherever the
worker runs: ``$FREESCALE_HOME`` when set, else the folder the installed ``flows`` package
lives in (``/app`` in the image, the clone on a host with ``pip install -e .``). A hard-coded
``/app`` crashed every run on a host process worker, and a process worker's own default is
a fresh temporary folder (where the relative entrypoint is not found and a relative store
path would vanish with the folder).
"""

from __future__ import annotations

import os
from pathlib import Path


def project_root() -> Path:
    """The folder holding the installed ``flows`` package (the project checkout)."""
    return Path(__file__).resolve().parents[1]


def enter_project(directory: str | None = None) -> dict:
    """``chdir`` to ``directory``, ``$FREESCALE_HOME`` or :func:`project_root`; return it."""
    d = Path(directory or os.environ.get("FREESCALE_HOME") or project_root()).expanduser()
    if not (d / "flows" / "generate_dataset.py").is_file():
        raise FileNotFoundError(
            f"{d} is not a FreeScale project folder (no flows/generate_dataset.py); set "
            "FREESCALE_HOME to the checkout (or /app in the image)")
    os.chdir(d)
    return {"directory": str(d)}
