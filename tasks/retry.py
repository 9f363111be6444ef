"""Which stage failures are worth a retry.

A retry helps when the failure came from the machine, not from the scene: a lost Dask worker,
a closed connection, a full or flaky file system, memory pressure from a concurrent scene.
It cannot help with bad input (every :class:`~freescale_core.errors.SceneError`: corrupt
image, unknown camera model, NaN Gaussians, ...) or a programming error (``ValueError``,
``TypeError``, ...), which fail the same way every time; those end the scene at once.
A retried stage resumes from its store checkpoint (``tasks.stage``), so nothing finished is
recomputed.
"""

from __future__ import annotations

from freescale_core.errors import FreeScaleError

RETRIES = 1
RETRY_DELAY_SECONDS = 5

# Exception class names (any module) that mean "the machine, not the scene".
_TRANSIENT_NAMES = {"KilledWorker", "CommClosedError", "StreamClosedError", "TimeoutError",
                    "ConnectionError", "ConnectionResetError", "BrokenPipeError",
                    "MemoryError", "ProcessLookupError"}


def is_transient(exc: BaseException | None) -> bool:
    """True for failures a retry may fix; False for bad input and programming errors."""
    if exc is None or isinstance(exc, (FreeScaleError, KeyboardInterrupt, SystemExit)):
        return False
    if type(exc).__name__ in _TRANSIENT_NAMES:
        return True
    if isinstance(exc, (ConnectionError, TimeoutError, MemoryError)):
        return True
    # OSError without being a missing/forbidden file: EIO, ENOSPC, ESTALE on a shared store
    return isinstance(exc, OSError) and not isinstance(
        exc, (FileNotFoundError, PermissionError, IsADirectoryError, NotADirectoryError))


def retry_condition(task, task_run, state) -> bool:
    """Prefect ``retry_condition_fn``: retry only transient failures."""
    try:
        exc = state.result(raise_on_failure=False)
    except BaseException as e:  # noqa: BLE001 - the state's own exception
        exc = e
    return is_transient(exc if isinstance(exc, BaseException) else None)


RETRY_OPTS = dict(retries=RETRIES, retry_delay_seconds=RETRY_DELAY_SECONDS,
                  retry_condition_fn=retry_condition)
