"""decod_rs.allocator: the heap keeps what a submap window freed, for the next window."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

from decod_rs.allocator import OFF_SWITCH, keep_freed_memory

# In a fresh process (the tuning is process-wide): allocate and free one 64-beam window's
# rows (20 MB), then report the free bytes glibc's heap keeps and the bytes in mmap blocks.
PROBE = """
import ctypes, sys
from decod_rs.allocator import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] != "default" else False
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in (
        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
        "fordblks", "keepcost")]
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.mallinfo2.restype = Info
window = 20 << 20
block = libc.malloc(window)
ctypes.memset(block, 1, window)
mapped = libc.mallinfo2().hblkhd
libc.free(block)
print(int(applied), mapped, libc.mallinfo2().fordblks)
"""


def _probe(mode: str, off: bool = False) -> tuple[bool, int, int]:
    env = {**os.environ, OFF_SWITCH: "0" if off else "1"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE, mode], capture_output=True, text=True, check=True, env=env
    ).stdout.split()
    return bool(int(out[0])), int(out[1]), int(out[2])


def test_a_freed_window_stays_in_the_heap_for_the_next_one() -> None:
    if platform.libc_ver()[0] != "glibc":
        # Only glibc is tuned; elsewhere the call says it did nothing.
        assert keep_freed_memory() is False
        return
    assert keep_freed_memory() is True and keep_freed_memory() is True  # once, idempotent
    window = 20 << 20
    # Untuned, glibc maps a block this large on its own and unmaps it when freed: the next
    # window's pages are new (page faults, zeroed by the kernel).
    applied, mapped, kept = _probe("default")
    assert not applied and mapped >= window and kept < window
    # Tuned, it comes from the heap and stays there once freed.
    applied, mapped, kept = _probe("tuned")
    assert applied and mapped < window and kept >= window
    # DECOD_KEEP_FREED_MEMORY=0 keeps glibc's defaults (python -m decod_rs.bench.allocator).
    applied, mapped, kept = _probe("tuned", off=True)
    assert not applied and mapped >= window and kept < window
