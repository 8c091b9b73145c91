"""The companion's memory settings for the path timing: glibc's allocator set to reuse
the large blocks it frees, and the start-up's objects frozen out of the collector's scans.

glibc serves a block of 128 kB or more from a fresh mmap and unmaps it when freed (its
mmap threshold, which it raises towards 32 MB only as such blocks come and go), so each
of the path timing's large numpy arrays is new memory that faults in page by page as it
is first written: timing a 100-pose path made ~3,300 minor faults (13 MB) and spent 11
ms of its ~60 ms in the kernel on this 2-vCPU host.  With the threshold at 32 MB and the
heap trimmed only past 64 MB of free space at its top, freed blocks serve the next
arrays: no faults, ~50 ms (`python bench/planning.py`, which sets it as the companion
does).  The cost: up to 64 MB freed stays with the process.  The real-time core does
not call this: its memory is locked and allocated up front (daemon.process.realtime).

The collector's full collections scan every live object; the companion holds ~230,000
after start-up (modules, compiled kernels), and the 20,000 waypoints of a 2,000-line
G-code path set off collections that doubled their making (240 ms against 116 ms with
the start-up frozen).  `freeze_start_up` moves what exists to the permanent generation
(gc.freeze), as the core does (drivers.gc_policy).
"""

from __future__ import annotations

import ctypes
import gc

M_TRIM_THRESHOLD = -1  # <malloc.h>
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 << 20  # bytes: glibc's largest on 64-bit systems
TRIM_THRESHOLD = 64 << 20  # bytes of free heap top kept before it is returned


def reuse_freed_memory() -> bool:
    """Keep freed large blocks in the heap (module docstring); False where the C library
    has no mallopt (not glibc) or refuses a setting."""
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is None:
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(
        mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD)
    )


def freeze_start_up() -> None:
    """Exempt every object that exists now from the collector's scans (module
    docstring): call once start-up is done."""
    gc.freeze()
