"""The firmware's line grammar, its parameter table and the web app's settings export."""

import json

import numpy as np
import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.bot_errors import BotError, OutOfRangeError
from flowerpose.hardware.protocol import (
    ENCODERS,
    ENDSTOPS,
    IDS,
    MOTION_PARAMETERS,
    PARAMETERS,
    checked_line,
    describe,
    fixed,
    move_line,
    parse_reply,
    read_settings,
    servo_line,
)


def test_the_table_names_every_parameter_the_client_uses_once():
    assert len(IDS) == len(PARAMETERS)
    used = {p for ids in MOTION_PARAMETERS.values() for p in ids}
    used |= set(ENDSTOPS.values()) | set(ENCODERS.values())
    assert used <= set(PARAMETERS)
    assert describe(101) == "101 (encoder_enabled_x)" and describe(9999) == "9999"


def test_settings_from_an_account_export_skip_the_record_and_the_approval(tmp_path):
    path = tmp_path / "export.json"
    path.write_text(json.dumps({"firmware_config": {
        "id": 3, "device_id": 9, "created_at": "2026-01-01", "updated_at": "2026-01-02",
        "api_migrated": True, "param_config_ok": 1, "movement_max_spd_x": 600.0,
        "encoder_enabled_x": 1, "movement_home_spd_x": None}}))
    assert read_settings(path) == {71: 600.0, 101: 1.0}
    path.write_text(json.dumps({"encoder_enabled_z": 0}))
    assert read_settings(path) == {103: 0.0}


@pytest.mark.parametrize("data, words", [
    ({"speed": 1}, "unknown firmware parameter 'speed'"),
    ({"encoder_enabled_x": "1"}, "encoder_enabled_x: the value must be a number"),
    ({"encoder_enabled_x": True}, "must be a number"),
    ({"id": 1}, "holds no firmware parameter"),
    ([1, 2], "expected a JSON object"),
])
def test_a_bad_export_names_the_file_and_the_key(tmp_path, data, words):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    with pytest.raises(InputError, match=words) as error:
        read_settings(path)
    assert "bad.json" in str(error.value)


def test_numbers_are_fixed_point_and_lines_never_hold_an_e():
    assert move_line((1e-7, 123456.789, -0.004)) == "G00 X0.00 Y123456.79 Z0.00"
    assert move_line((1e21, -2.5e-3, 12.345), (200, 200, 40)) == \
        "G00 X1000000000000000000000.00 Y0.00 Z12.35 A200 B200 C40"  # 12.345 is 12.3449..
    assert fixed(-0.001) == "0.00" and fixed(2.675) == "2.67"
    with pytest.raises(OutOfRangeError, match="finite"):
        move_line((np.nan, 0, 0))
    with pytest.raises(BotError, match="emergency stop"):
        checked_line("F22 P71 V1e3")
    with pytest.raises(BotError):
        checked_line("F82 @")
    assert servo_line(6, 90.4) == "F61 P6 V90"
    with pytest.raises(OutOfRangeError, match="only pins 4, 5, 6 and 11"):
        servo_line(7, 90)
    with pytest.raises(OutOfRangeError, match="0-180"):
        servo_line(5, 181)


def test_replies_are_parsed_through_line_noise():
    reply = parse_reply("\ufffd\ufffd#R82 X1.20 Y-3.00 Z0.00 Q17")
    assert (reply.code, reply.q, reply.values) == ("R82", 17, {"X": 1.2, "Y": -3.0, "Z": 0.0})
    echo = parse_reply("R08 *G00 X1.00 Y2.00 Z3.00 Q5*")
    assert echo.code == "R08" and echo.q is None  # the echoed Q is the command's
    version = parse_reply("R83 6.6.23.G.genesisK14 Q3")
    assert version.text == "6.6.23.G.genesisK14" and version.values == {}
    assert parse_reply("R03 V31 Q9").values == {"V": 31.0}
    assert parse_reply("%$#") is None


# --- connecting ---------------------------------------------------------------------
