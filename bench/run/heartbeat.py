"""Progress lines for the long study commands (``sampling``, ``extract``): a line when a stage
starts, and while it runs a line at least every ``every_s`` seconds, so that no command is
silent for minutes (a costly reference integral can take several).

    with Heartbeat(print_line, every_s=30) as beat:
        beat.stage("sphere.camera.64x64: the rendering integral on 64 rays")
        ...  # each later beat.stage(...) starts the next stage

The periodic lines come from a daemon thread and say which stage is running and for how long
(``<stage>: still running, 61 s``); ``progress`` must therefore accept calls from another thread
(``print`` with ``flush=True`` does).
"""

from __future__ import annotations

import threading
import time
from typing import Callable


class Heartbeat:
    """``progress(line)`` at each :meth:`stage` and every ``every_s`` seconds of a stage after
    that, until the ``with`` block exits.  ``every_s`` > 0."""

    def __init__(self, progress: Callable[[str], None] | None, every_s: float = 30.0):
        if not every_s > 0:
            raise ValueError(f"every_s must be > 0 seconds, got {every_s}")
        self.progress, self.every_s = progress, float(every_s)
        self._lock = threading.Lock()
        self._stage, self._since = "", time.monotonic()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def stage(self, text: str) -> None:
        """Say that ``text`` starts now (a line at once), and beat on it from now on."""
        with self._lock:
            self._stage, self._since = text, time.monotonic()
        if self.progress:
            self.progress(text)

    def say(self, text: str) -> None:
        """A line now, the stage unchanged (e.g. a stage's result)."""
        if self.progress:
            self.progress(text)

    def _beat(self) -> None:
        while not self._stop.wait(self.every_s):
            with self._lock:
                stage, since = self._stage, self._since
            if stage and self.progress:
                self.progress(f"{stage}: still running, {time.monotonic() - since:.0f} s")

    def __enter__(self) -> "Heartbeat":
        if self.progress:
            self._thread = threading.Thread(target=self._beat, name="isobench-heartbeat", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
