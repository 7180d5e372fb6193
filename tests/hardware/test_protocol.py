"""The firmware parameter table and the web app's settings export."""

import json

import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.motion import FIRMWARE_PARAMETERS
from flowerpose.hardware.protocol import (
    ENCODERS,
    ENDSTOPS,
    IDS,
    PARAMETERS,
    describe,
    read_settings,
)


def test_the_table_names_every_parameter_the_client_uses_once():
    assert len(IDS) == len(PARAMETERS)
    used = {p for ids in FIRMWARE_PARAMETERS.values() for p in ids}
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
