"""One logger: what is said along the way, how much (-q / -v), and the time left."""

import logging

from flowerpose.log import LOG, VERBOSITY_ENV, Tally, configure, eta


def test_eta_says_the_time_so_far_and_left_at_the_rate_so_far():
    assert eta(10.0, 1, 3) == "(10 s in, about 20 s left)"
    assert eta(10.0, 3, 3) == "(10 s in)"
    assert eta(150.0, 1, 2) == "(2 min 30 s in, about 2 min 30 s left)"
    assert eta(5.0, 0, 2) == "(5 s in, about ? left)"


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
        assert capsys.readouterr().err.startswith("[1/2] plant a (0 s in, about 0 s left)")
        configure(1)
        assert LOG.isEnabledFor(logging.DEBUG)
        import os

        assert os.environ[VERBOSITY_ENV] == "1"  # what spawned workers read
    finally:
        configure(0)


def test_other_libraries_warnings_are_debug_lines_during_a_command(monkeypatch, capfd):
    """Python warnings (numpy's RuntimeWarnings) and other libraries' log records, raised
    while a command runs, are shown with -v only, as this logger's lines."""
    import warnings

    import numpy as np

    from flowerpose import cli
    from flowerpose.cli import jobs

    def noisy(args):
        np.log(np.zeros(1))  # RuntimeWarning: divide by zero
        logging.getLogger("matplotlib.font_manager").warning("building the font cache")
        return 0

    monkeypatch.setattr(jobs, "cmd_bench", noisy)
    showwarning = warnings.showwarning
    try:
        assert cli.main(["bench"]) == 0
        assert capfd.readouterr().err == ""
        assert cli.main(["bench", "-v"]) == 0
        said = capfd.readouterr().err.splitlines()
        assert any(line.startswith("RuntimeWarning (") and "divide by zero" in line
                   for line in said), said
        assert "matplotlib.font_manager: building the font cache" in said
    finally:
        configure(0)
    assert warnings.showwarning is showwarning  # Python's own again after the command
    assert not any(type(h).__name__ == "_LibraryRecords" for h in logging.getLogger().handlers)


def test_open3d_keeps_its_warnings_to_itself_unless_asked(capfd):
    from flowerpose.log import open3d

    def empty_search():
        o3d = open3d()  # as every module of the project takes it
        o3d.geometry.PointCloud().remove_radius_outlier(3, 0.01)  # "Failed due to no data"

    try:
        configure(0)
        empty_search()
        assert capfd.readouterr() == ("", "")
        configure(1)
        empty_search()
        assert "Failed due to no data" in capfd.readouterr().out
    finally:
        configure(0)


def test_library_output_takes_what_matches_and_passes_on_the_rest(capfd):
    import os

    from flowerpose.log import library_output

    with library_output(r"^RPly: ") as said:
        os.write(2, b"RPly: Unexpected end of file\nsomeone else's line\n")
        os.write(1, b"RPly: on stdout too\n")
    assert sorted(said) == ["RPly: Unexpected end of file", "RPly: on stdout too"]
    assert capfd.readouterr() == ("", "someone else's line\n")


def test_a_loop_that_reports_now_and_then_says_its_count_and_time_left(capsys):
    try:
        configure(0)
        with Tally(300, "pairs") as tally:
            for done in range(1, 301):
                tally.advance(1, f"matched {done}/300 pairs" if done % 100 == 0 else None)
        lines = capsys.readouterr().err.splitlines()
        assert [line.split(" (")[0] for line in lines] == [
            "matched 100/300 pairs", "matched 200/300 pairs", "matched 300/300 pairs"]
        assert all("left)" in line for line in lines[:-1]) and tally.done == 300
        assert lines[-1].endswith("(0 s in)")  # done: the time it took
    finally:
        configure(0)
