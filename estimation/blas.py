"""Fewer BLAS threads while a registration runs: OpenBLAS's idle workers spin.

numpy and scipy bring OpenBLAS. It runs a large enough matrix product on every core and then
keeps its worker threads spinning, in case another product comes soon. A registration already
keeps two cores busy: its own thread and its second thread
(``estimation.registration.gicp._reverse_executor``). Its BLAS products are small, and the
spinning workers took the second thread's core. They went on spinning after the
registration returned, so whatever ran next was slowed too.

Measured on the scan's 15k-point halves, two cores, 20 starts (/work/exp35/order.py):
- after a registration, the process burnt 35-80 ms of CPU in a 100 ms sleep (0.1 ms after
  Open3D GICP);
- GICP-SE(3) took 167 ms after an Open3D run and 192-195 ms after one of ours; Semantic-ICP
  197 and 225-229 ms; Open3D itself 199 and 220-231 ms;
- with one BLAS thread (``OPENBLAS_NUM_THREADS=1``): GICP-SE(3) 154-157 ms, Semantic-ICP
  183-188 ms, Open3D 199-204 ms, whatever ran before.

:func:`blas_threads` limits every BLAS library loaded in the process (threadpoolctl) for a
``with`` block and restores the earlier limits after it (after the last of several threads'
blocks). It changes a process-wide setting, so it is opt-out: ``OCTOFACTOR_BLAS_THREADS=keep``
in the environment leaves BLAS alone.
"""
from __future__ import annotations

import contextlib
import os
import threading
from collections.abc import Iterator

_CONTROLLER = None  # threadpoolctl's view of the loaded libraries (made at the first use)
_LOCK = threading.Lock()
_HOLDERS = 0  # contexts inside blas_threads now (registrations in several threads)
_LIMITER = None  # the limit they hold: restored when the last one leaves


def _left_alone() -> bool:
    return os.environ.get("OCTOFACTOR_BLAS_THREADS") == "keep"


def find_libraries_now() -> None:
    """Find the libraries (:func:`find_libraries`) now, unless BLAS is left alone: at the
    import of a module whose calls limit them, so that its first call does not pay for it."""
    if not _left_alone():
        find_libraries()


def find_libraries():
    """threadpoolctl's controller of the BLAS libraries loaded in the process, made at the
    first call (threadpoolctl's import and its scan of the loaded libraries: about 6.5 ms);
    :func:`blas_threads` limits those. Libraries loaded after the first call are not limited."""
    global _CONTROLLER
    if _CONTROLLER is None:
        from threadpoolctl import ThreadpoolController

        _CONTROLLER = ThreadpoolController()
    return _CONTROLLER


@contextlib.contextmanager
def blas_threads(threads: int) -> Iterator[None]:
    """A context in which the process's BLAS libraries use at most ``threads`` threads (one at
    least), and after which they have their earlier limits again.

    The limit is process-wide, so contexts entered in several threads share one: the first
    sets it, the last one to leave restores the earlier limits, in whatever order they
    leave. Does nothing where ``OCTOFACTOR_BLAS_THREADS=keep`` is set."""
    if _left_alone():
        yield
        return
    global _HOLDERS, _LIMITER
    with _LOCK:
        if _HOLDERS == 0:
            _LIMITER = find_libraries().limit(limits=max(int(threads), 1), user_api="blas")
        _HOLDERS += 1
    try:
        yield
    finally:
        with _LOCK:
            _HOLDERS -= 1
            if _HOLDERS == 0:
                _LIMITER.restore_original_limits()
                _LIMITER = None
