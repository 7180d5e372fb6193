"""User-facing errors: the command line turns these into one line and exit status 2."""

from __future__ import annotations

from pathlib import Path


def rebuild_error(cls: type, message: str, state: dict) -> Exception:
    """An exception of `cls` with its message and attributes, without calling its
    __init__ (whose arguments differ between classes)."""
    error = cls.__new__(cls)
    Exception.__init__(error, message)
    error.__dict__.update(state)
    return error


class PicklableError(Exception):
    """An exception that survives pickling whatever its __init__ takes, so one raised in a
    worker process reaches the command line intact (Exception's default pickling calls
    __init__ with the message alone)."""

    def __reduce__(self):
        return rebuild_error, (type(self), str(self), dict(self.__dict__))


class InputError(PicklableError):
    """Bad input from the user (a file, a value, a device): reported as one line, exit 2.

    `source` names what was wrong (a file path, a config key, a device) so the message
    can always say where the problem is.
    """

    def __init__(self, source: str | Path, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")


class JobsFailed(PicklableError):
    """Jobs of one stage that failed on every try, named by plant, once the stage's other
    jobs have finished (their results are kept); exit 1. Where every cause was bad input
    the pool raises the first one's own `InputError` instead (`eval.pool.failed`).
    `retried`: each was tried again (on Ray) before it counted as failed."""

    def __init__(self, stage: str, failures: list[tuple[str, BaseException]],
                 retried: bool = True):
        self.stage = stage
        self.failures = [(label, one_line(error)) for label, error in failures]
        super().__init__(f"{len(failures)} {stage} job(s) failed"
                         + (" after a retry" if retried else "") + ": "
                         + "; ".join(f"{label}: {line}" for label, line in self.failures))


def one_line(error: BaseException) -> str:
    """An exception as one line: its type and its first line of text."""
    text = str(error).strip()
    return f"{type(error).__name__}: {text.splitlines()[0]}" if text else type(error).__name__


#: The optional packages, by the extra that installs them (pyproject.toml).
EXTRAS = {"mujoco": "sim", "pyrender": "sim", "trimesh": "sim", "OpenGL": "sim",
          "pycolmap": "recon", "farmbot": "bot", "serial": "bot", "paho": "bot",
          "onnxruntime": "onnx", "jwt": "bot", "ray": "ray", "optuna": "tune",
          "sqlalchemy": "tune", "ompl": "plan"}


def missing_extra(module: str, needed_for: str) -> InputError | None:
    """The one-line error for an optional package that is not installed (`module`, a
    top-level name), or None when it is not one of flowerpose's extras."""
    extra = EXTRAS.get(module.split(".")[0])
    if extra is None:
        return None
    return InputError(needed_for, f"needs the [{extra}] extra ({module} is not installed): "
                      f"pip install 'flowerpose[{extra}]'")
