"""Helpers for the tests that talk MAVLink over real sockets on 127.0.0.1 (test_live, test_run)."""

from __future__ import annotations

import socket
import threading
from typing import Any

from onlinecal.io.base import ImuData
from onlinecal.testing.sender import send_session


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Sender:
    """Runs ``fn(stop_event)`` in a thread; its result or exception is kept."""

    def __init__(self, fn) -> None:
        self.stop = threading.Event()
        self.result = None
        self.error: BaseException | None = None

        def run() -> None:
            try:
                self.result = fn(self.stop)
            except BaseException as e:  # reported by the test, not lost in the thread
                self.error = e

        self.thread = threading.Thread(target=run, daemon=True)
        self.thread.start()

    def finish(self) -> None:
        self.stop.set()
        self.thread.join(10.0)
        assert not self.thread.is_alive(), "sender thread did not end"
        if self.error is not None:
            raise self.error


def sending(data: ImuData, url: str, **kw: Any) -> Sender:
    """The test vehicle (``send_session`` of ``data`` to ``url``) in a thread."""
    return Sender(lambda stop: send_session(data, url, stop_event=stop, **kw))
