"""The command line run inside a test, as a shell runs it."""

from flowerpose.cli import main


def run_cli(capsys, *argv) -> tuple[int, str, str]:
    """`flowerpose ARGV` (each argument made a string): its exit status, argparse's own
    exits included, and what it printed to stdout and stderr."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exit_:
        code = exit_.code
    out, err = capsys.readouterr()
    return code, out, err
