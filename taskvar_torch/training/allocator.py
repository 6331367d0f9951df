"""glibc's allocator kept from returning freed memory to the OS between learner updates.

Each update frees and reallocates the same few MB; glibc's default trim and mmap thresholds hand
them back to the kernel and fault them in again (docs/benchmarks.md). :func:`keep_freed_memory`
raises both once; no number computed changes. ``TASKVAR_MALLOC=default`` leaves glibc as it is; off
glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

M_TRIM_THRESHOLD = -1  # glibc malloc.h
M_MMAP_THRESHOLD = -3
MMAP_MAX_MIB = 32  # glibc's ceiling for M_MMAP_THRESHOLD on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX)

_result: bool | None = None  # the first call's outcome: later calls (every update phase) reuse it


def keep_freed_memory(trim_mib: int = 512, mmap_mib: int = MMAP_MAX_MIB) -> bool:
    """Set glibc's ``M_TRIM_THRESHOLD`` to ``trim_mib`` and ``M_MMAP_THRESHOLD`` to ``mmap_mib``
    MiB (once per process); returns whether the settings are in place (``False`` off glibc or
    with ``TASKVAR_MALLOC=default``)."""
    global _result
    if os.environ.get("TASKVAR_MALLOC", "") == "default":
        return False
    if _result is None:
        _result = _set_thresholds(trim_mib, mmap_mib)
    return _result


def _set_thresholds(trim_mib: int, mmap_mib: int) -> bool:
    name = ctypes.util.find_library("c")  # may run ldconfig: once per process, not per update
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = mallopt(M_MMAP_THRESHOLD, min(mmap_mib, MMAP_MAX_MIB) << 20) == 1
    return mallopt(M_TRIM_THRESHOLD, trim_mib << 20) == 1 and ok


__all__ = ["keep_freed_memory"]
