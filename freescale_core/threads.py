"""The one place that sets compute-thread counts (torch intra-op, numba) for a block of work.

torch's intra-op thread count is *process-wide*: when scenes run in threads of one process
(the thread runner, local Dask workers), a per-call ``set -> run -> restore`` lets one scene's
restore reset another's setting mid-run (scene A saves 2 and sets 1, scene B saves 1, A ends
and restores 2 while B still trains). :func:`compute_threads` therefore leases the torch
setting: the first concurrent holder saves the previous value and sets it, later holders share
it (a different request is recorded and ignored: the first setting wins while any holder
runs), and only the last holder to leave restores it.

numba's ``set_num_threads`` is thread-local (numba >= 0.49), so it is set per calling thread
and restored on exit without any lease.
"""

from __future__ import annotations

import threading
from contextlib import contextmanager
from typing import Iterator

import torch

_LOCK = threading.Lock()
_HOLDERS = 0
_SAVED: int | None = None
_ACTIVE: int | None = None


def torch_lease_state() -> dict:
    """``{"holders", "active", "saved"}``: the torch thread lease, for tests and stats."""
    with _LOCK:
        return {"holders": _HOLDERS, "active": _ACTIVE, "saved": _SAVED}


@contextmanager
def compute_threads(torch_threads: int | None = None, numba_threads: int | None = None
                    ) -> Iterator[dict]:
    """Run the block with ``torch_threads`` torch intra-op threads (process-wide lease) and
    ``numba_threads`` numba threads (this thread only); ``None`` leaves a setting alone.

    Yields ``{"torch": granted, "numba": granted}`` (``granted["torch"]`` differs from the
    request when another holder set a different count first).
    """
    global _HOLDERS, _SAVED, _ACTIVE
    granted: dict = {"torch": torch.get_num_threads(), "numba": None}
    leased = False
    if torch_threads is not None:
        with _LOCK:
            if _HOLDERS == 0:
                _SAVED = torch.get_num_threads()
                _ACTIVE = int(torch_threads)
                torch.set_num_threads(_ACTIVE)
            _HOLDERS += 1
            granted["torch"] = _ACTIVE
        leased = True
    prev_numba = None
    if numba_threads is not None:
        import numba

        prev_numba = numba.get_num_threads()
        numba.set_num_threads(max(1, min(int(numba_threads), numba.config.NUMBA_NUM_THREADS)))
        granted["numba"] = numba.get_num_threads()
    try:
        yield granted
    finally:
        if prev_numba is not None:
            import numba

            numba.set_num_threads(prev_numba)
        if leased:
            with _LOCK:
                _HOLDERS -= 1
                if _HOLDERS == 0:
                    torch.set_num_threads(_SAVED)
                    _SAVED = _ACTIVE = None
