"""glibc malloc tuning for the long-running recorder (no-ops on other C libraries).

The recorder allocates and frees a compressed chunk (up to :data:`.layout.CHUNK_SIZE` bytes)
and a zstd context (about 1 MB) a few times a second, from the Zenoh threads and its own.
glibc's defaults make that fragment: each thread gets its own arena (up to 8 per core) and the
mmap threshold adapts upward whenever a large mmapped block is freed (up to 32 MB), so later
blocks of that size come from arena heaps, whose free holes are not given back. Measured in
the 100-robot soak of ``bench/bench_chaos.py``: resident memory grew 5-11 % in 12-25 min with
the defaults, 2.7 % in 10 min with ``MALLOC_ARENA_MAX=2``. :func:`tune` caps the arenas and
fixes the mmap threshold (which turns its adaptation off: a large block the heap cannot serve
from free space is mmapped, and unmapped when freed); :func:`trim` gives free heap pages back
(``malloc_trim(0)``; glibc >= 2.8 releases free pages inside the heap too, not only at its
top).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
from functools import cache
from typing import Final

log = logging.getLogger(__name__)

# mallopt parameters, glibc malloc/malloc.h
M_MMAP_THRESHOLD: Final = -3
M_ARENA_MAX: Final = -8

#: Arenas for the recorder: its threads mostly wait on one lock, more arenas buy nothing.
ARENA_MAX: Final = 2
#: Allocations at least this large are mmapped (and unmapped on free): the chunk buffers and
#: zstd contexts, not the many small payloads.
MMAP_THRESHOLD: Final = 128 * 1024


@cache
def _glibc() -> ctypes.CDLL | None:
    """The process's glibc, or None (musl, macOS, Windows...)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.gnu_get_libc_version  # noqa: B018  (AttributeError: not glibc)
        libc.mallopt  # noqa: B018
        libc.malloc_trim  # noqa: B018
    except (OSError, AttributeError):
        return None
    libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    libc.mallopt.restype = ctypes.c_int
    libc.malloc_trim.argtypes = [ctypes.c_size_t]
    libc.malloc_trim.restype = ctypes.c_int
    return libc


def tune(arena_max: int = ARENA_MAX, mmap_threshold: int = MMAP_THRESHOLD) -> bool:
    """Cap malloc arenas and fix the mmap threshold; True if applied (glibc). Call at process
    start, before the threads that allocate exist (arenas already made stay)."""
    libc = _glibc()
    if libc is None:
        log.debug("not glibc: malloc left as it is")
        return False
    ok = bool(libc.mallopt(M_ARENA_MAX, arena_max)) and bool(
        libc.mallopt(M_MMAP_THRESHOLD, mmap_threshold)
    )
    if not ok:
        log.warning("mallopt refused the recorder's malloc settings")
    return ok


def trim() -> bool:
    """Give free heap memory back to the OS (``malloc_trim(0)``); True if some was (glibc)."""
    libc = _glibc()
    return libc is not None and bool(libc.malloc_trim(0))


def rss_kib() -> int | None:
    """This process's resident memory in KiB (Linux ``/proc/self/statm``), else None."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") // 1024
