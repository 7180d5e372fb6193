"""One logger: what is said along the way, how much (-q / -v), and the time left."""

import logging
import time

from flowerpose.log import LOG, VERBOSITY_ENV, Tally, configure, eta


def test_eta_says_the_time_so_far_and_left_at_the_rate_so_far():
    start = time.perf_counter() - 10.0
    assert eta(start, 1, 3) == "(10 s, about 20 s left)"
    assert eta(start, 3, 3) == "(10 s)"
    assert eta(time.perf_counter() - 150.0, 1, 2) == "(2 min 30 s, about 2 min 30 s left)"


def test_verbosity_sets_what_is_said_here_and_in_workers(monkeypatch, capsys):
    monkeypatch.delenv(VERBOSITY_ENV, raising=False)
    try:
        configure(-1)
        LOG.info("progress")
        LOG.warning("note: kept")
        with Tally(2) as tally:
            tally.finished("plant a")
        assert capsys.readouterr().err == "note: kept\n"
        configure(0)
        with Tally(2) as tally:
            tally.finished("plant a")
        assert capsys.readouterr().err.startswith("[1/2] plant a (0 s, about 0 s left)")
        configure(1)
        assert LOG.isEnabledFor(logging.DEBUG)
        import os

        assert os.environ[VERBOSITY_ENV] == "1"  # what spawned workers read
    finally:
        configure(0)
