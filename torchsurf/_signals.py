"""Interrupts held back across a step that must not be cut in two."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM until the block ends, then take them.

    For steps an interrupt must not split: VTK's import (or its EGL probe), which crashed the
    process (exit 139) instead of exiting 143, and the two renames that put a run's picture
    and record in place together. Python runs signal handlers in the main thread, so recording
    them there holds a signal whichever thread the system gave it to; elsewhere (no handlers
    can be set) nothing is held.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []
    held = (signal.SIGINT, signal.SIGTERM)
    previous = {number: signal.signal(number, lambda number, frame: pending.append(number))
                for number in held}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        if pending:
            signal.raise_signal(pending[0])
