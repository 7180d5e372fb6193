"""Fixtures of the hardware tests."""

import signal

import pytest


@pytest.fixture
def watchdog():
    """The test ends within 20 s: a protocol bug fails it instead of hanging the suite. A
    test may lengthen its own limit with signal.setitimer."""
    def expire(signum, frame):
        raise TimeoutError("the test ran past its time limit")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, 20.0)
    yield
    signal.setitimer(signal.ITIMER_REAL, 0.0)
    signal.signal(signal.SIGALRM, previous)
