"""Errors cross process boundaries intact (eval and sweep run stages in worker processes)."""

import pickle

import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.bot_errors import (
    CommandTimeoutError,
    ConnectionLostError,
    StallError,
    error_for_code,
)
from flowerpose.hardware.kinematics import UnreachableError


@pytest.mark.parametrize("error", [
    InputError("grid.pixel_size_m", "too fine"),
    UnreachableError("scan waypoint 3", "unreachable: gantry X", 3, ("gantry X",)),
    StallError("G00 X1 Y2 Z3", 32),
    error_for_code(1, "G00"),
    CommandTimeoutError("F82", 15.0),
    ConnectionLostError("/dev/ttyACM0", "unplugged"),
])
def test_errors_survive_pickling(error):
    back = pickle.loads(pickle.dumps(error))
    assert type(back) is type(error) and str(back) == str(error)
    assert back.__dict__ == error.__dict__
