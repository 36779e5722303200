"""One background thread that runs queued calls in the order they were queued."""
from __future__ import annotations

import logging
import queue
import threading
from typing import Optional

log = logging.getLogger("diffuser_lab.recording")


class SerialThread:
    """Runs ``submit``-ted calls one after another on a daemon thread.

    Args:
        name: the thread's name.
        maxsize: calls that may wait; ``submit`` blocks beyond (a slow consumer slows the
            producer down instead of filling the memory).
        stop_on_error: after a call raises, skip the queued calls and keep the exception in
            :attr:`error` (for a writer whose later records would be unreadable); otherwise log
            a warning and go on.
    """

    def __init__(self, name: str, maxsize: int, stop_on_error: bool):
        self.error: Optional[BaseException] = None
        self._stop_on_error = stop_on_error
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self.error is not None:
                continue  # drain after a failure
            fn, args = item
            try:
                fn(*args)
            except BaseException as exc:  # noqa: BLE001 - kept, or logged: never kills the thread
                if self._stop_on_error:
                    self.error = exc
                else:
                    log.warning("recording failed: %s: %s", type(exc).__name__, exc)

    def submit(self, fn, *args) -> None:
        self._queue.put((fn, args))

    def close(self) -> None:
        """Run what is queued, then stop the thread."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
