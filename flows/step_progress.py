"""A Prefect progress artifact fed with steps done (the training flows share it)."""

from __future__ import annotations

import time


class StepProgress:
    """Steps done -> a Prefect progress artifact ``key`` (updated at most every ``every`` s;
    no artifact, silently, outside a run or without an API)."""

    def __init__(self, total: int, key: str, description: str, every: float = 5.0):
        self.total, self.every, self._last = total, every, 0.0
        self.artifact = None
        try:
            from prefect.artifacts import create_progress_artifact

            self.artifact = create_progress_artifact(progress=0.0, key=key,
                                                     description=description)
        except Exception:  # noqa: BLE001 - no API or no run context: no artifact
            self.artifact = None

    def __call__(self, step: int, *_rest) -> None:
        now = time.monotonic()
        if self.artifact is None or (step < self.total and now - self._last < self.every):
            return
        self._last = now
        try:
            from prefect.artifacts import update_progress_artifact

            update_progress_artifact(self.artifact, progress=min(100.0, 100.0 * step / self.total))
        except Exception:  # noqa: BLE001
            self.artifact = None
