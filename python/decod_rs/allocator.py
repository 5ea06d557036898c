"""The C allocator tuned for decod's working set (performance only; no output changes).

A submap window of a 64-beam sensor accumulates about 1.2 M points: 19 MB of rows, as much
again for the voxel sort's buffers, allocated and freed once per window, two windows in
flight, twice per run when the submaps are rebuilt. glibc's allocator serves blocks that
large with fresh ``mmap`` pages or returns the top of its heap to the system once more than
128 KB is free there, so every window paid for its pages again: on the 66 s shield log with
64 beams, a turn and uneven drift, 180,000-220,000 page faults and 0.7-0.9 s of system time
in a 5-6 s run.

:func:`keep_freed_memory` asks glibc (``mallopt``) to serve blocks up to 32 MB from its heap,
never to trim the heap, and to grow it 256 MB at a time. Measured on that log (``decod run
--no-plots``, alone, interleaved, two runs each): 56,000-58,000 page faults, 0.37-0.39 s of
system time, 4.6-4.9 s instead of 5.5-5.7 s; the peak memory 286 MB instead of 268 MB (the
heap keeps what a window freed for the next one). Every output is the same: only where
memory comes from changes.

Process-wide, so it is called where the process is decod's own: ``decod`` commands
(:mod:`decod_rs.cli`), the batch workers' tasks and the matrix workers; a program that
imports ``decod_rs`` decides for itself (call it, or set the ``MALLOC_TRIM_THRESHOLD_`` and
``MALLOC_TOP_PAD_`` environment variables). Elsewhere than glibc (macOS, musl) it does
nothing, and ``DECOD_KEEP_FREED_MEMORY=0`` turns it off (glibc's defaults, for comparison:
``python -m decod_rs.bench.allocator`` measures both).

:func:`peak_memory_mb` reports what the process has held at most (``report.json``
``peak_memory_mb``, printed by ``decod run``), the figure this tuning trades against.
"""

from __future__ import annotations

import ctypes
import functools
import os
import platform
import sys

__all__ = ["OFF_SWITCH", "keep_freed_memory", "peak_memory_mb"]

#: ``DECOD_KEEP_FREED_MEMORY=0`` leaves glibc's defaults.
OFF_SWITCH = "DECOD_KEEP_FREED_MEMORY"

#: glibc's ``mallopt`` parameters (``malloc.h``).
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3

#: Blocks up to this size come from the heap (glibc's ceiling for the setting, 64-bit).
HEAP_BLOCKS_UP_TO = 32 << 20
#: The heap is never trimmed (the largest value ``mallopt`` takes: an ``int``).
NEVER_TRIM = 2**31 - 1
#: The heap grows by this much at a time.
TOP_PAD = 256 << 20


@functools.cache
def keep_freed_memory() -> bool:
    """Tune glibc's allocator for decod (module docs), once per process; whether it was
    (False off glibc, with ``DECOD_KEEP_FREED_MEMORY=0``, or when glibc refused a
    setting)."""
    if os.environ.get(OFF_SWITCH) == "0":
        return False
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    settings = (
        (M_MMAP_THRESHOLD, HEAP_BLOCKS_UP_TO),
        (M_TRIM_THRESHOLD, NEVER_TRIM),
        (M_TOP_PAD, TOP_PAD),
    )
    return all(mallopt(param, value) == 1 for param, value in settings)


def peak_memory_mb() -> float | None:
    """The process's peak resident memory so far, in MB (10^6 bytes; ``getrusage``'s
    ``ru_maxrss``: kilobytes on Linux, bytes on macOS); None where the platform does not
    say (Windows). For ``decod run`` the run's own; in a batch worker or a program that
    imports ``decod_rs``, the process's over everything it ran. ``report.json``
    ``peak_memory_mb``: what a log needs, which grows with it (``docs/measurements.md``,
    "Long logs": 0.68 GB for 400 m of pipe, 33 minutes of log)."""
    try:
        import resource
    except ImportError:
        return None
    peak = float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
    return peak / 1e6 if sys.platform == "darwin" else peak * 1024 / 1e6
