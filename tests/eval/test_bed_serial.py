"""A bed through the physical bot's code: `field --sim --via-farmduino` drives the serial
Farmduino backend on a virtual Farmduino (its firmware's motion timing, 100 times real
time) with the simulated camera, and the bot does not wait for the computer."""

import json

import pytest
from beds import BED, SMALL

from flowerpose.cli import main


@pytest.mark.slow
def test_a_bed_through_the_serial_backend_keeps_the_bot_busy(tmp_path, capsys):
    bed = tmp_path / "bed.toml"
    bed.write_text(BED)
    out = tmp_path / "run"
    assert main(["field", "--sim", "--via-farmduino", "--bed", str(bed), "--out", str(out),
                 *SMALL, "-q"]) == 0
    assert "2 of 2 plants detected" in capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    for entry in report["plants"]:
        assert entry["found_visible"] >= 1
        scan = json.loads((out / "plants" / entry["plant"] / "scan" / "scan.json").read_text())
        assert scan["source"]["backend"] == "sim via virtual Farmduino"
        assert scan["status"] == "complete"
    times = report["timing_s"]
    # the bot films the next plant while the computer works on the last one
    assert times["bot_waiting"] < 0.05 * times["after_first_plant"]
    assert times["after_first_plant"] > 0


def test_the_time_scale_belongs_to_the_virtual_farmduino(tmp_path, capsys):
    bed = tmp_path / "bed.toml"
    bed.write_text(BED)
    assert main(["field", "--sim", "--bed", str(bed), "--out", str(tmp_path / "o"),
                 "--time-scale", "10"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--via-farmduino" in err and err.count("\n") == 0
    assert not (tmp_path / "o").exists()
