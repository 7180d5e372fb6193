"""Processes that end cleanly: SIGTERM as an exception in the command, and worker processes
that do not outlive the command that started them."""

from __future__ import annotations

import ctypes
import signal
import sys
import threading


class Terminated(BaseException):
    """SIGTERM arrived: the command unwinds (its `finally` blocks run, so what it was
    writing is finished or left as it was) and exits with 143, as the shell expects."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated


def terminate_cleanly() -> None:
    """Turn SIGTERM into `Terminated` (only the main thread can take signals)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _raise_terminated)


#: prctl's option that sends the child a signal when its parent dies (Linux).
_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Ask the kernel to end this worker when the process that started it dies, even by
    SIGKILL, so no renderer or pipeline worker is left holding memory. For worker
    initializers; a no-op where prctl is unavailable."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):
        return
