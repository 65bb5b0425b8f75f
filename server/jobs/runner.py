"""Where blocking work runs: worker threads, at most ``max_concurrent_evals`` at a time, each in a scratch
folder of this process's; the event loop only waits. Memory a job freed goes back to the system after it."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import threading
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, TypeVar, cast

import anyio
import anyio.to_thread

from ..observability import AdmissionState
from .scratch import ScratchSpace

__all__ = ["Runner", "release_memory"]

T = TypeVar("T")


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        return cast(Callable[[int], int], libc.malloc_trim)
    except (OSError, AttributeError):  # not glibc
        return None


def release_memory() -> None:
    """Hand the heap's free pages back to the system. glibc keeps what a request freed (a refused upload of
    a million small objects left the service 100 MB above idle); ``malloc_trim`` returns it. A no-op where
    the C library is not glibc."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


class Runner:
    def __init__(self, capacity: int, admission: AdmissionState, scratch_space: ScratchSpace) -> None:
        self.capacity = capacity
        self.admission = admission
        self.scratch_space = scratch_space
        self._limiter: anyio.CapacityLimiter | None = None
        self._running_lock = threading.Lock()

    def open(self) -> None:
        """Called from the lifespan (the limiter belongs to the event loop)."""
        self._limiter = anyio.CapacityLimiter(self.capacity)

    async def run(self, func: Callable[..., T], *args: Any, release: bool = True) -> T:
        """Run blocking work on a worker thread, at most ``capacity`` at once; afterwards the memory it freed
        goes back to the system (:func:`release_memory`) unless ``release`` is False: work that reads no file
        (accepting an upload as a job) frees only a few large buffers, which the C library unmaps by itself,
        and trimming after it would only make the next request fault its pages in again."""

        def job() -> T:
            with self._running_lock:
                self.admission.running += 1
            try:
                return func(*args)
            finally:
                with self._running_lock:
                    self.admission.running -= 1
                if release:
                    release_memory()

        return await anyio.to_thread.run_sync(job, limiter=self._limiter)

    def scratch(self) -> AbstractContextManager[Path]:
        """A new scratch folder of this process's (:class:`~kitti_eval_server.jobs.scratch.ScratchSpace`), removed on
        the way out."""
        return self.scratch_space.folder()
