"""Graceful shutdown: drain first, then let the ASGI server stop.

The application's lifespan installs :class:`Drainer` on SIGTERM, in front of the server's own handler
(uvicorn's, under ``kitti-eval serve``, ``uvicorn ...main:app`` and the Docker image alike). On the first
SIGTERM the service starts draining (``Service.draining``): ``/readyz`` answers 503 at once, so a load
balancer stops sending; a new evaluation request is answered 503 with Retry-After and
``Connection: close``; the evaluations already admitted run to the end and are committed, their responses sent.
When none is left, or ``KITTI_EVAL_SHUTDOWN_GRACE_S`` after the signal at the latest, the signal is handed to
the server's handler, and uvicorn's own shutdown runs: it stops listening, lets the requests still open finish
within its graceful timeout, and runs the application's shutdown. A second SIGTERM is handed on at once.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import threading
import time
from types import FrameType
from typing import Any

from .service import Service

__all__ = ["Drainer"]

log = logging.getLogger("kitti_eval.server")
_TICK_S = 0.05


class Drainer:
    def __init__(self, service: Service) -> None:
        self.service = service
        self.previous: Any = None
        self.started: float | None = None
        self._task: asyncio.Task[None] | None = None

    def install(self) -> bool:
        """Put the drain in front of the current SIGTERM handler; False where signals cannot be caught here
        (not the main thread: an application run by a test client)."""
        if threading.current_thread() is not threading.main_thread():
            return False
        self.previous = signal.signal(signal.SIGTERM, self._on_term)
        self._task = asyncio.get_running_loop().create_task(self._watch())
        return True

    def uninstall(self) -> None:
        if self._task is not None:
            self._task.cancel()
            self._task = None
        if self.previous is not None and signal.getsignal(signal.SIGTERM) == self._on_term:
            signal.signal(signal.SIGTERM, self.previous)

    def _on_term(self, sig: int, frame: FrameType | None) -> None:
        if self.started is not None:  # a second SIGTERM: stop now
            self._hand_on()
            return
        self.started = time.monotonic()
        self.service.draining.set()
        log.info(
            "SIGTERM: draining (%d evaluation requests admitted), at most %g s",
            self.service.admission.in_flight,
            self.service.settings.shutdown_grace_s,
        )

    async def _watch(self) -> None:
        while True:
            await asyncio.sleep(_TICK_S)
            if self.started is None:
                continue
            in_flight = self.service.admission.in_flight
            if in_flight and time.monotonic() - self.started < self.service.settings.shutdown_grace_s:
                continue
            if in_flight:
                log.warning("shutdown grace period over with %d evaluation requests admitted", in_flight)
            self._hand_on()
            return

    def _hand_on(self) -> None:
        """The signal to the handler that was there before (uvicorn's: it starts its shutdown)."""
        previous, self.previous = self.previous, None
        if previous is None:
            return
        signal.signal(signal.SIGTERM, previous)
        signal.raise_signal(signal.SIGTERM)
