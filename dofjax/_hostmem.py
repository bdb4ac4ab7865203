"""Keep large XLA CPU programs' temporary memory between calls (opt-in, like the compile cache).

XLA's CPU runtime allocates a program's temporaries as one buffer per call; above glibc's 32 MiB
mmap threshold each call maps fresh pages and the kernel faults in and zeroes them.
`tune_host_memory` caps XLA's heaps at `HEAP_BYTES` and has glibc keep freed memory for reuse.
Results are unchanged; nothing in dofjax calls it (the allocator is the process owner's
choice). Why and when it helps: docs/performance.md, "Large images on Linux".
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys
import warnings

HEAP_BYTES = 30 << 20  # below glibc's 32 MiB ceiling for requests it serves from its heap
FLAG = "--xla_multiheap_size_constraint_per_heap"
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # <malloc.h>
_MMAP_THRESHOLD = 32 << 20  # glibc's largest allowed value
_TRIM_THRESHOLD = 1 << 30


def _glibc():
    """The C library if it is glibc (which has `mallopt`), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 (glibc only)
        libc.mallopt  # noqa: B018
    except (OSError, AttributeError):
        return None
    return libc


def _backends_started() -> bool:
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without the query: assume the worst
        return True


def tune_host_memory() -> dict[str, bool]:
    """Let repeated calls of large CPU programs reuse their memory instead of faulting it in.

    Call once, before the first JAX computation of the process (the XLA part is read when
    JAX starts its backend). Opt-in: it changes the whole process's allocator (see the
    module docstring). Pays off for programs with more than 32 MiB of temporaries (at 512 x
    512: `jax.jacfwd` / `jax.grad` of a defocus);
    a 256 x 256 fit does not change.

    Returns:
        {"xla": whether XLA's heaps are limited (now, or already by the user's `XLA_FLAGS`),
        "allocator": whether glibc was told to keep freed memory (False off glibc)}.

    Warns (RuntimeWarning) when JAX's backend has already started: then only the allocator
    part applies; put `--xla_multiheap_size_constraint_per_heap=31457280` in `XLA_FLAGS`
    before starting Python, or give a jitted function `jax.jit(f, compiler_options=
    {"xla_multiheap_size_constraint_per_heap": 31457280})` (that program only).
    """
    flags = os.environ.get("XLA_FLAGS", "")
    xla = FLAG in flags
    if not xla:
        if _backends_started():
            warnings.warn(
                "tune_host_memory: JAX's backend has already started, so XLA's heaps keep "
                f"their size; call it before the first JAX computation or set XLA_FLAGS="
                f"{FLAG}={HEAP_BYTES}", RuntimeWarning, stacklevel=2)
        else:
            os.environ["XLA_FLAGS"] = f"{flags} {FLAG}={HEAP_BYTES}".strip()
            xla = True
    libc = _glibc()
    allocator = libc is not None and bool(
        libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD)
        and libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD))
    return {"xla": xla, "allocator": allocator}
