"""Keep freed memory in the process for the next iteration's arrays (glibc's malloc).

A registration allocates the same large temporaries every iteration: per-pair arrays of a
few hundred kilobytes to a few megabytes (whitening matrices, Jacobians, candidate lists).
glibc serves blocks above its mmap threshold (128 KiB at start, raised as such blocks are
freed) with fresh pages from the kernel and gives the top of its heap back beyond its trim
threshold, so each of those arrays is faulted in page by page again: on a 10k-point
registration 14k page faults in a new process's first call and about 4k in every later one
(2 us a fault on this project's virtual machines).

:func:`keep_freed_memory` raises both thresholds once (``mallopt``: blocks up to 32 MiB come
from the heap, which keeps up to 128 MiB of freed memory), so a process faults its working
set in once. Measured (benchmarks/registration.py ``--start-up``; one 10k-point pair): page
faults in the first call 14.3k -> 5.0k, in a warm call 4.1k -> under 100.

It changes the whole process's allocator, so it is opt-out: ``OCTOFACTOR_KEEP_HEAP=0`` in the
environment leaves malloc alone, and so do glibc's own settings (``MALLOC_MMAP_THRESHOLD_``,
``MALLOC_TRIM_THRESHOLD_``, ``GLIBC_TUNABLES``) when present. Elsewhere than glibc it does
nothing.
"""
from __future__ import annotations

import ctypes
import os
import sys

MMAP_THRESHOLD = 32 << 20  # bytes: glibc's largest (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD = 128 << 20  # bytes of freed memory kept at the heap's top
_M_TRIM_THRESHOLD = -1  # glibc's mallopt parameters (malloc.h)
_M_MMAP_THRESHOLD = -3
_ENV_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")
_state: bool | None = None  # None: not tried yet


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds once per process; True where they are raised
    (now or by an earlier call), False where left alone (opted out, settings of the user's,
    not glibc)."""
    global _state
    if _state is None:
        _state = _raise_thresholds()
    return _state


def _raise_thresholds() -> bool:
    if os.environ.get("OCTOFACTOR_KEEP_HEAP", "1") == "0":
        return False
    if any(name in os.environ for name in _ENV_SETTINGS):
        return False  # (the user's own malloc settings win)
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None)
        # (glibc only: musl's mallopt does nothing)
        glibc, mallopt = libc.gnu_get_libc_version, libc.mallopt
    except (OSError, AttributeError):
        return False
    glibc.restype = ctypes.c_char_p
    if glibc() is None:
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # (the trim threshold first: setting either stops glibc's own adjustment of both)
    return bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)
                and mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
