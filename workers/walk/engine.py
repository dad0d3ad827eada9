"""Process-wide set-up of the compute engine: done explicitly, once, where an engine starts.

Importing :mod:`workers` changes nothing outside it.  :func:`init_engine` makes the two
process-wide changes the compiled walk relies on for its speed; it is idempotent and called by
:func:`workers.run.shard.run_shard` (every walk) and by :mod:`workers.walk.kernels` before it compiles
or loads a kernel, so nothing else needs to call it:

- compiled CPU kernels run without the GIL (:func:`_release_gil_in_compiled_kernels`), so shards
  on several Python threads of one process overlap;
- glibc keeps freed buffers in the process (:func:`_keep_freed_memory_in_process`), so the
  compiled step's temporaries are not page-faulted in again on every call.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading

__all__ = ["init_engine"]

_lock = threading.Lock()
_done = False


def init_engine() -> None:
    """Apply the process-wide settings of the module docstring (once per process)."""
    global _done
    with _lock:
        if _done:
            return
        _release_gil_in_compiled_kernels()
        _keep_freed_memory_in_process()
        _done = True


def _release_gil_in_compiled_kernels() -> None:
    """Let compiled CPU kernels run without the GIL, so shards on several Python threads run in
    parallel (torch 2.13's inductor calls its C++ kernels holding the GIL).

    The kernels only touch raw buffers whose tensors the calling frame keeps alive, so releasing
    the GIL around the call is safe.  This edits the template of the generated Python binding
    (part of the kernel's cache key, so kernels built without it are not reused); if a future
    torch changes that template, nothing is changed and shards simply do not overlap.
    """
    try:  # torch's private module, imported here rather than at module level: it may be missing
        from torch._inductor.codecache import CppPythonBindingsCodeCache as Cache
    except ImportError:  # pragma: no cover - other torch versions
        return
    template = getattr(Cache, "call_entry_function", None)
    if template == "kernel({}); Py_RETURN_NONE;":
        Cache.call_entry_function = "Py_BEGIN_ALLOW_THREADS kernel({}); Py_END_ALLOW_THREADS Py_RETURN_NONE;"


def _keep_freed_memory_in_process() -> None:
    """Stop glibc from returning the compiled step's temporary buffers to the kernel.

    Each call of a compiled step allocates and frees intermediate buffers of 128 KiB and more:
    at glibc's default thresholds every one is a fresh mmap (or a heap trim), so its pages are
    faulted in and zeroed again on every call -- about a quarter of the walk's time here.  Raising
    the mmap threshold to its maximum (32 MiB) and the trim threshold keeps them on the heap for
    reuse.  Only the allocator's policy changes; elsewhere than glibc this does nothing.
    """
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = libc.mallopt if libc is not None else None
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        return
    if mallopt is None:  # pragma: no cover
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # glibc malloc.h
    mallopt(m_mmap_threshold, 32 << 20)
    mallopt(m_trim_threshold, 1 << 30)
