"""The guard battery: a run compared flower by flower with its accepted values passes when
nothing changed and fails when a change loses flowers or turns normals; bad batteries are
one line."""

import json

import pytest
from realplants import write_real_plant

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.guard import BATTERY, load_battery, run_guard

BATTERY_TEXT = """
[battery]
version = 1

[[entry]]
name = "plant"
source = "real"
plant = "plant"

[[entry]]
name = "plant-thin"
source = "real"
plant = "plant"
thin = [0.5]
cut = [0.25]
repeats = 2
"""


@pytest.fixture
def battery(tmp_path):
    path = tmp_path / "battery.toml"
    path.write_text(BATTERY_TEXT)
    return load_battery(path)


@pytest.mark.slow
def test_an_unchanged_run_passes_and_a_worse_one_fails_on_the_same_flowers(tmp_path, battery):
    folder = write_real_plant(tmp_path / "plant", "candidates")
    accepted = tmp_path / "accepted.json"
    first = run_guard(battery, battery.entries, tmp_path / "a", [folder], accepted,
                      workers=1, accept=True)
    assert [r["verdict"] for r in first["entries"].values()] == ["new", "new"]
    kept = json.loads(accepted.read_text())
    assert kept["battery_version"] == 1 and set(kept["entries"]) == {"plant", "plant-thin"}
    # Flowers keyed by plant, level and repeat: the thinned entry's are all distinct.
    thin = kept["entries"]["plant-thin"]
    assert len({p["plant"] for p in thin["plants"]}) == 4 and thin["visible"] == 16
    again = run_guard(battery, battery.entries, tmp_path / "b", [folder], accepted, workers=1)
    assert again["passed"]
    assert all(r["verdict"] == "pass" for r in again["entries"].values())
    assert again["entries"]["plant"]["paired"]["fits"]["plane"]["mean_difference"] == 0.0
    # A corolla test far too strict loses flowers...
    worse = run_guard(battery, battery.entries[:1], tmp_path / "c", [folder], accepted,
                      workers=1, overrides=({"pose.petal_max_radius": 0.3,
                                             "cluster.min_coverage": 3.0},))
    assert not worse["passed"]
    row = worse["entries"]["plant"]
    assert row["verdict"] == "worse" and any("recall" in r for r in row["reasons"])
    # ... and the accepted values stay as they were unless accepted.
    assert json.loads(accepted.read_text()) == kept


def test_the_shipped_battery_reads_and_bad_ones_are_refused(tmp_path, capsys):
    shipped = load_battery()
    assert shipped.path == str(BATTERY)
    names = [e.name for e in shipped.entries]
    assert {"scan-6", "oracle-20", "real3", "real3-thin"} <= set(names)
    assert all(e.seed >= 100 for e in shipped.entries if e.source != "real")
    with pytest.raises(InputError, match="entries"):
        shipped.select(["nope"])
    bad = tmp_path / "bad.toml"
    for text, message in (
            ("[battery]\nversion = 1\n[[entry]]\nname = 'a'\nsource = 'oracle'\n", "plants"),
            ("[battery]\nversion = 1\n[[entry]]\nname = 'a'\nsource = 'real'\nx = 1\n",
             "unknown key"),
            ("[battery]\n[[entry]]\nname = 'a'\nsource = 'real'\nplant = 'p'\n", "version")):
        bad.write_text(text)
        with pytest.raises(InputError, match=message):
            load_battery(bad)
    assert main(["guard", "--battery", str(bad), "--out", str(tmp_path / "out")]) == 2
    assert "version" in capsys.readouterr().err
    (tmp_path / "b.toml").write_text(BATTERY_TEXT)
    assert main(["guard", "--battery", str(tmp_path / "b.toml"), "--out",
                 str(tmp_path / "out2")]) == 2
    assert "--real DIR" in capsys.readouterr().err
