"""The core install: the pipeline runs without the simulator, photogrammetry or the bot's
packages, and a command that needs one of those extras says which, in one line."""

import subprocess
import sys

import numpy as np
import pytest

from flowerpose.cloudio import Cloud, write_cloud
from flowerpose.errors import EXTRAS

BLOCK = "import sys\n" + "".join(f"sys.modules[{m!r}] = None\n" for m in EXTRAS) + (
    "from flowerpose.cli import main\nsys.exit(main(sys.argv[1:]))\n")


def _core(*args):
    """flowerpose as a core install runs it: every optional package unimportable."""
    return subprocess.run([sys.executable, "-c", BLOCK, *map(str, args)], capture_output=True,
                          text=True, timeout=300)


@pytest.mark.slow
def test_detect_runs_on_the_core_install_and_the_extras_are_named(tmp_path):
    rng = np.random.default_rng(0)
    leaves = Cloud(rng.random((2000, 3)) * [0.3, 0.3, 0.2],
                   np.tile([50, 120, 40], (2000, 1)).astype(np.uint8))
    cloud = write_cloud(tmp_path / "leaves.ply", leaves)
    done = _core("detect", cloud, "--out", tmp_path / "det")
    assert done.returncode == 0 and (tmp_path / "det" / "flowers.json").exists(), done.stderr
    for args, extra in ((["plant", "--seed", "1", "--out", tmp_path / "p"], "sim"),
                        (["dataset", "--plants", "2", "--out", tmp_path / "d"], "sim"),
                        (["detect", cloud, "--out", tmp_path / "o", "--detector",
                          "onnx:model.onnx"], "onnx")):
        done = _core(*args)
        assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
        assert done.stderr.strip().endswith(f"pip install 'flowerpose[{extra}]'")
        assert done.stderr.count("\n") == 1
    frames = tmp_path / "frames"
    frames.mkdir()
    (frames / "camera.json").write_text("{}")
    done = _core("reconstruct", frames, "--out", tmp_path / "rec")
    assert done.returncode == 2 and "[recon] extra (pycolmap" in done.stderr, done.stderr


def test_the_virtual_farmduino_serves_on_the_core_install():
    """It keeps the gantry's joints itself, on a pseudo-terminal: no simulator, no pyserial."""
    import signal

    board = subprocess.Popen([sys.executable, "-c", BLOCK, "farmduino", "--virtual"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             # as from a terminal, even where this runs as a background job
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        path = board.stdout.readline().strip()
        assert path.endswith("ttyFarmduino"), board.stderr.read() if board.poll() else path
        board.send_signal(signal.SIGINT)  # Ctrl-C stops it
        assert board.wait(timeout=60) == 0
        assert "Traceback" not in board.stderr.read()
    finally:
        board.kill()
        board.wait()


def test_every_commands_help_works_on_the_core_install():
    """`--help` of every command with every extra unimportable: exit 0, no traceback."""
    script = "import sys\n" + "".join(f"sys.modules[{m!r}] = None\n" for m in EXTRAS) + (
        "import contextlib, io\n"
        "from flowerpose.cli import build_parser\n"
        "parser = build_parser()\n"
        "commands = next(a for a in parser._actions if a.dest == 'command').choices\n"
        "for name in commands:\n"
        "    code = None\n"
        "    with contextlib.redirect_stdout(io.StringIO()):\n"
        "        try:\n"
        "            build_parser().parse_args([name, '--help'])\n"
        "        except SystemExit as done:\n"
        "            code = done.code\n"
        "    print(name, code)\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert "Traceback" not in done.stderr, done.stderr
    codes = dict(line.split() for line in done.stdout.splitlines())
    assert len(codes) >= 20 and set(codes.values()) == {"0"}, codes
