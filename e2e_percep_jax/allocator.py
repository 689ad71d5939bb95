"""Let XLA:CPU reuse freed buffers instead of faulting fresh pages in on every call.

glibc's malloc serves a request above its mmap threshold (dynamic, at most 32 MiB) with pages of its
own and unmaps them on free, and it returns the heap's free top to the system above its trim
threshold. A jitted function whose buffers cross those limits then gets new pages every call, which
the kernel must fault in and zero. On this project's 2-core VM that was 600-1,800 page faults and
1.5-3.7 ms of system time per 32-frame ``sensors.observe`` call (~10 ms of wall time), and its cost
swung with the host's load: one-second medians fell from ~3,400 to 1,400-1,900 frames/s in some
seconds. With the limits below, the same call faults ~20 pages and no 1.5-s block fell below 2,447
frames/s.

The cost: freed memory up to ``trim_threshold_mib`` stays in the process instead of going back to
the system. A process-wide setting, so the launchers in ``experiments/`` call it and the library
never does on its own; call it from your own entry point if you generate batches or run the
perceiver in a loop.
"""

import ctypes
import ctypes.util

_M_TRIM_THRESHOLD = -1  # mallopt parameters, from glibc's malloc.h
_M_MMAP_THRESHOLD = -3
_MIB = 1 << 20
MMAP_THRESHOLD_MIB = 256
TRIM_THRESHOLD_MIB = 512
# The same setting for a process started afresh (glibc reads it at start-up), e.g. the benchmark's peer.
GLIBC_TUNABLES = (
    f"glibc.malloc.mmap_threshold={MMAP_THRESHOLD_MIB * _MIB}:glibc.malloc.trim_threshold={TRIM_THRESHOLD_MIB * _MIB}"
)


def keep_freed_buffers(
    mmap_threshold_mib: int = MMAP_THRESHOLD_MIB, trim_threshold_mib: int = TRIM_THRESHOLD_MIB
) -> bool:
    """Serves allocations below ``mmap_threshold_mib`` from the heap and keeps up to
    ``trim_threshold_mib`` of freed heap. Returns whether it took effect: False where the C library
    is not glibc (macOS, musl), where this does nothing."""
    if not 0 < mmap_threshold_mib <= trim_threshold_mib:
        raise ValueError(
            f"mmap_threshold_mib={mmap_threshold_mib}, trim_threshold_mib={trim_threshold_mib}: "
            "need 0 < mmap_threshold_mib <= trim_threshold_mib"
        )
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):  # no C library found, or one without mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    mmap_set = mallopt(_M_MMAP_THRESHOLD, mmap_threshold_mib * _MIB)  # 1 on success (musl's stub: 0)
    trim_set = mallopt(_M_TRIM_THRESHOLD, trim_threshold_mib * _MIB)
    return mmap_set == 1 and trim_set == 1
