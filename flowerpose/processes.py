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


#: What SIGTERM should do in this process, once asked: raise `Terminated` (the command)
#: or end it quietly (a worker); None: whatever the process was given.
_sigterm_action = None


def _set_sigterm(action) -> None:
    global _sigterm_action
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, action)
        _sigterm_action = action


def terminate_cleanly() -> None:
    """Turn SIGTERM into `Terminated` (only the main thread can take signals)."""
    _set_sigterm(_raise_terminated)


def reclaim_sigterm() -> None:
    """Take SIGTERM back after a library took it: pycolmap's glog installs a handler that
    prints a C stack dump and kills the process. Only where this module set it."""
    if _sigterm_action is not None:
        _set_sigterm(_sigterm_action)


#: prctl's option that sends the child a signal when its parent dies (Linux).
_PR_SET_PDEATHSIG = 1


def quiet_worker() -> None:
    """A worker initializer: Ctrl-C (which the terminal sends to every process of the
    group) is left to the command, which stops its workers itself, so none prints a
    traceback; SIGTERM ends the worker quietly; the worker dies with the command
    (`die_with_parent`); and it says as much as the command (`log.configure_worker`)."""
    from flowerpose.log import configure_worker

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _set_sigterm(signal.SIG_DFL)
    die_with_parent()
    configure_worker()


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
