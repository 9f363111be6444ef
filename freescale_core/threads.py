"""The one place that sets compute-thread counts (torch intra-op, numba) for a block of work.

torch's intra-op thread count is *process-wide*: when scenes run in threads of one process
(the thread runner, local Dask workers), a per-call ``set -> run -> restore`` lets one scene's
restore reset another's setting mid-run (scene A saves 2 and sets 1, scene B saves 1, A ends
and restores 2 while B still trains). :func:`compute_threads` therefore leases the torch
setting: the first concurrent holder saves the previous value and sets it, later holders share
it (a different request is recorded and ignored: the first setting wins while any holder
runs), and only the last holder to leave restores it.

numba's ``set_num_threads`` is thread-local (numba >= 0.49), so it is set per calling thread
and restored on exit without any lease. OpenBLAS's count is process-wide like torch's and is
leased the same way (:func:`blas_threads`).
"""

from __future__ import annotations

import contextlib
import ctypes
import threading
from contextlib import contextmanager
from typing import Callable, Iterator


class ThreadLease:
    """A process-wide thread count shared by concurrent holders: the first holder saves the
    current count and sets its own, later holders share it (a different request is ignored:
    the first setting wins while any holder runs), the last to leave restores the saved one.
    ``get`` / ``set`` read and write the library's count (torch, OpenBLAS)."""

    def __init__(self, get: Callable[[], int], set: Callable[[int], None]):
        self._get, self._set = get, set
        self._lock = threading.Lock()
        self.holders = 0
        self.saved: int | None = None
        self.active: int | None = None

    def state(self) -> dict:
        """``{"holders", "active", "saved"}``, for tests and stats."""
        with self._lock:
            return {"holders": self.holders, "active": self.active, "saved": self.saved}

    @contextmanager
    def hold(self, n: int) -> Iterator[int]:
        """Hold the lease for the block; yields the count in force (``n`` or the first
        holder's)."""
        with self._lock:
            if self.holders == 0:
                self.saved = int(self._get())
                self.active = int(n)
                self._set(self.active)
            self.holders += 1
            granted = self.active
        try:
            yield granted
        finally:
            with self._lock:
                self.holders -= 1
                if self.holders == 0:
                    self._set(self.saved)
                    self.saved = self.active = None


def _torch_get() -> int:
    import torch

    return torch.get_num_threads()


def _torch_set(n: int) -> None:
    import torch

    torch.set_num_threads(n)


TORCH_LEASE = ThreadLease(_torch_get, _torch_set)


def torch_lease_state() -> dict:
    """``{"holders", "active", "saved"}``: the torch thread lease, for tests and stats."""
    return TORCH_LEASE.state()


@contextmanager
def compute_threads(torch_threads: int | None = None, numba_threads: int | None = None
                    ) -> Iterator[dict]:
    """Run the block with ``torch_threads`` torch intra-op threads (process-wide lease) and
    ``numba_threads`` numba threads (this thread only); ``None`` leaves a setting alone.

    Yields ``{"torch": granted, "numba": granted}`` (``granted["torch"]`` differs from the
    request when another holder set a different count first).
    """
    with contextlib.ExitStack() as stack:
        granted: dict = {"torch": None, "numba": None}
        if torch_threads is not None:
            granted["torch"] = stack.enter_context(TORCH_LEASE.hold(torch_threads))
        else:
            granted["torch"] = _torch_get()
        if numba_threads is not None:
            import numba

            prev_numba = numba.get_num_threads()
            stack.callback(numba.set_num_threads, prev_numba)
            numba.set_num_threads(max(1, min(int(numba_threads),
                                             numba.config.NUMBA_NUM_THREADS)))
            granted["numba"] = numba.get_num_threads()
        yield granted


_BLAS: list | None = None
_BLAS_FIND_LOCK = threading.Lock()


def _find_openblas():
    """``(get, set)`` of the OpenBLAS numpy is linked to, read from ``/proc/self/maps``
    (Linux; None when not found)."""
    try:
        with open("/proc/self/maps") as fh:
            paths = sorted({ln.split()[-1] for ln in fh if "openblas" in ln.lower()
                            and ".so" in ln})
        for p in paths:
            lib = ctypes.CDLL(p)
            for pre, suf in (("scipy_openblas_", "64_"), ("openblas_", "64_"),
                             ("scipy_openblas_", ""), ("openblas_", "")):
                g, s = f"{pre}get_num_threads{suf}", f"{pre}set_num_threads{suf}"
                if hasattr(lib, g) and hasattr(lib, s):
                    getf, setf = getattr(lib, g), getattr(lib, s)
                    getf.restype, setf.argtypes = ctypes.c_int, [ctypes.c_int]
                    return getf, setf
    except OSError:
        pass
    return None


def _openblas_controls():
    """``(get, set)`` of the OpenBLAS numpy is linked to (Linux; None when not found), looked
    up once per process.

    The lookup is serialised: it used to publish "not found" before scanning, so a scene whose
    selection started while another scene's lookup was still scanning got None, ran its GEMMs
    at the process default (2 threads) and stored ``nms_overlap`` 2-3 float32 ulps off a lone
    run's (fresh-clone CI, stop 29; ``tests/test_threads.py``).
    """
    global _BLAS
    if _BLAS is None:
        with _BLAS_FIND_LOCK:
            if _BLAS is None:
                _BLAS = [_find_openblas()]
    return _BLAS[0]


# used only when _openblas_controls() found the library
_BLAS_LEASE = ThreadLease(lambda: _openblas_controls()[0](),
                          lambda n: _openblas_controls()[1](n))


@contextmanager
def blas_threads(n: int | None):
    """Run the block with ``n`` OpenBLAS threads; ``None``/0 = unchanged.

    The NMS and graph GEMMs are many medium-sized products; when several processes share the
    cores, multi-threaded OpenBLAS spin-waits and can cost several times the CPU of one
    thread, so the selection core runs them single-threaded by default
    (``GraphConfig.blas_threads``).

    OpenBLAS's count is process-wide and its results depend on it (float32 products differ in
    the last bits between 1 and 2 threads), so the setting is *leased* like torch's
    (:class:`ThreadLease`): a per-call set/restore let one scene's
    restore switch another scene's GEMMs to 2 threads mid-selection.
    """
    if not n or _openblas_controls() is None:
        yield
        return
    with _BLAS_LEASE.hold(int(n)):
        yield
