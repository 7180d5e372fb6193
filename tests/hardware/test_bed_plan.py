"""A bed of plants: the bed file read (TOML or CSV) or refused in one line naming the plant,
every scan checked against the bot's reach and the neighbours before anything moves, and
the visits ordered to keep the gantry's travel short."""

from importlib.resources import files

import pytest

from flowerpose.errors import InputError
from flowerpose.hardware.flights.bed_plan import (
    PLANT_HEIGHT_M,
    PLANT_RADIUS_M,
    Bed,
    BedPlant,
    plan_bed,
    read_bed,
)
from flowerpose.hardware.flights.scan_plan import ScanConfig
from flowerpose.scan_geometry import ScanPathConfig

EXAMPLE = files("flowerpose.assets") / "beds" / "example-4.toml"
NARROW = ScanConfig(path=ScanPathConfig(cylinder_radius_m=0.3))


def _toml(tmp_path, text: str):
    path = tmp_path / "bed.toml"
    path.write_text(text)
    return path


def test_a_toml_and_a_csv_bed_give_the_same_plants_with_the_defaults_where_none_is_given(
        tmp_path):
    toml = _toml(tmp_path, '[[plant]]\nname = "a"\nx = 0.7\ny = 0.75\n\n'
                           '[[plant]]\nname = "b"\nx = 1.5\ny = 0.8\nheight = 0.3\n')
    csv = tmp_path / "bed.csv"
    csv.write_text("name,x,y,height,radius\na,0.7,0.75,,\nb,1.5,0.8,0.3,\n")
    expected = [BedPlant("a", 0.7, 0.75, PLANT_HEIGHT_M, PLANT_RADIUS_M),
                BedPlant("b", 1.5, 0.8, 0.3, PLANT_RADIUS_M)]
    assert read_bed(toml) == read_bed(csv) == Bed(expected, ScanConfig())


def test_the_bed_file_carries_its_scan_settings():
    bed = read_bed(EXAMPLE)
    assert bed.scan.path.cylinder_radius_m == 0.3
    assert [plant.name for plant in bed.plants] == ["row-1", "row-2", "row-3", "row-4"]


@pytest.mark.parametrize("text, words", [
    ('[[plant]]\nname = "a"\nx = 0.7\n', "plant 'a': 'y' is missing"),
    ('[[plant]]\nname = "a"\nx = "left"\ny = 0.7\n', "plant 'a': 'x' must be a number"),
    ('[[plant]]\nname = "a"\nx = 0.7\ny = 0.7\nwidth = 1\n', "plant 1: unknown key 'width'"),
    ('[[plant]]\nname = "a b"\nx = 0.7\ny = 0.7\n', "plant 1: 'name' must be"),
    ('[[plant]]\nx = 0.7\ny = 0.7\n', "plant 1: 'name' must be"),
    ('[[plant]]\nname = "a"\nx = 0.7\ny = 0.7\n[[plant]]\nname = "a"\nx = 1.5\ny = 0.7\n',
     "plant 'a' is named twice"),
    ('[[plant]]\nname = "a"\nx = 0.7\ny = nan\n', "'y' must be a number"),
    ('[scan]\npause_s = 1.0\n', "no plant in the bed"),
    ('[scan.path]\ncylinder_radius = 0.3\n[[plant]]\nname = "a"\nx = 1\ny = 0.7\n',
     "scan.path.cylinder_radius: no such setting"),
    ('[beds]\n', "unknown key 'beds'"),
    ('plant = 3\n', "'plant' must be an array of tables"),
])
def test_a_bad_bed_file_is_refused_naming_the_file_and_the_plant(tmp_path, text, words):
    path = _toml(tmp_path, text)
    with pytest.raises(InputError, match="^" + str(path)) as error:
        read_bed(path)
    assert words in str(error.value) and "\n" not in str(error.value)


def test_a_csv_without_the_position_columns_or_a_file_of_another_kind_is_refused(tmp_path):
    csv = tmp_path / "bed.csv"
    csv.write_text("plant,x\na,0.7\n")
    with pytest.raises(InputError, match="'name' is missing"):
        read_bed(csv)
    other = tmp_path / "bed.json"
    other.write_text("{}")
    with pytest.raises(InputError, match=r"\.toml or \.csv"):
        read_bed(other)
    with pytest.raises(InputError, match="not found"):
        read_bed(tmp_path / "none.csv")


def test_the_visits_follow_the_row_whatever_the_files_order():
    bed = read_bed(EXAMPLE)
    shuffled = Bed([bed.plants[i] for i in (2, 0, 3, 1)], bed.scan)
    plan = plan_bed(shuffled)
    assert [plant.name for plant in plan.plants] == ["row-1", "row-2", "row-3", "row-4"]
    # From the far end the row is flown the other way.
    far = plan_bed(shuffled, start=(2.8, 1.3, 0.6))
    assert [plant.name for plant in far.plants] == ["row-4", "row-3", "row-2", "row-1"]
    assert plan.duration_s == pytest.approx(sum(s.duration_s for s in plan.scans)
                                            + sum(plan.travel_s))
    assert len(plan.table()) == 6 and plan.table()[1].split()[1] == "row-1"


def test_a_plant_out_of_reach_is_refused_before_anything_moves_naming_it():
    plants = [BedPlant("near", 1.0, 0.75), BedPlant("edge", 2.6, 0.75)]
    with pytest.raises(InputError, match=r"^plant edge: .*gantry X.*fits a plant"):
        plan_bed(Bed(plants))


def test_neighbours_the_scan_would_hit_are_refused_naming_both():
    plants = [BedPlant("a", 0.9, 0.75), BedPlant("b", 1.55, 0.75)]
    with pytest.raises(InputError, match=r"^plant a: .* from plant b .*move the plants apart"):
        plan_bed(Bed(plants))
    # A narrower cylinder keeps clear of them.
    assert [p.name for p in plan_bed(Bed(plants, NARROW)).plants] == ["a", "b"]


#: The web app's points of a small garden: two plants of one crop, a weed, and a plant whose
#: name is no folder's.
GARDEN = [
    {"id": 11, "pointer_type": "Plant", "name": "Strawberry", "x": 700.0, "y": 615.0, "z": 0,
     "radius": 180.0},
    {"id": 13, "pointer_type": "Weed", "name": "Dandelion", "x": 1000.0, "y": 615.0, "z": 0},
    {"id": 12, "pointer_type": "Plant", "name": "Strawberry", "x": 2000.0, "y": 615.0, "z": 0,
     "radius": 0},
]


def test_a_gardens_plants_from_the_web_app_make_a_bed_in_the_bed_frame():
    from flowerpose.hardware.flights.bed_plan import (
        PLANT_HEIGHT_M,
        PLANT_RADIUS_M,
        bed_from_points,
    )
    from flowerpose.hardware.geometry import PAPER_BOT, farmbot_mm_to_bed

    plants = [p for p in GARDEN if p["pointer_type"] == "Plant"]
    plants.append({"id": 14, "pointer_type": "Plant", "name": "Alpine strawberry!",
                   "x": 1400.0, "y": 615.0, "radius": 25.0})  # the app's default spread
    bed = bed_from_points(plants)
    assert [p.name for p in bed.plants] == ["strawberry-11", "strawberry-12",
                                            "alpine-strawberry-14"]
    first = farmbot_mm_to_bed([700.0, 615.0, 0.0], PAPER_BOT)
    assert (bed.plants[0].x, bed.plants[0].y) == pytest.approx((first[0], first[1]))
    # the app's radius where it is more than a plant's default reach, never less
    assert [p.radius for p in bed.plants] == pytest.approx([0.18, PLANT_RADIUS_M,
                                                            PLANT_RADIUS_M])
    assert all(p.height == PLANT_HEIGHT_M for p in bed.plants)
    with pytest.raises(InputError, match="no plant in the garden"):
        bed_from_points([])
    with pytest.raises(InputError, match="'Strawberry' \\(id 11\\) has no numeric x and y"):
        bed_from_points([{**plants[0], "x": None}])


def test_field_cloud_plans_the_accounts_garden_and_moves_nothing(tmp_path, capsys,
                                                                 monkeypatch):
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from cloud_fakes import FakeDevice, fake_factory, make_token

    from flowerpose.cli import main
    from flowerpose.hardware.backends import cloud_bot

    device = FakeDevice()
    device.points = GARDEN
    factory = fake_factory(device)
    monkeypatch.setattr(cloud_bot, "farmbot_client", factory)
    monkeypatch.setenv("FARMBOT_TOKEN", json.dumps(make_token()))
    out = tmp_path / "bed"
    assert main(["field", "--cloud", "--out", str(out), "--dry-run"]) == 0
    shown = capsys.readouterr().out
    assert "strawberry-11" in shown and "strawberry-12" in shown
    assert "dandelion" not in shown.lower() and "2 plants" in shown
    assert device.calls == [("api_get", "points")]  # read the garden; no move, no status
    assert not out.exists()
    # filming the garden needs the head's camera: one line, before anything connects
    calls = list(device.calls)
    assert main(["field", "--cloud", "--out", str(out)]) == 2
    assert "--camera" in capsys.readouterr().err and not out.exists()
    assert device.calls == calls + [("api_get", "points")]
    # an expired token: one line naming the server, never the token
    device.points = []
    monkeypatch.setattr(factory.clients[0].__class__, "api_get",
                        lambda self, endpoint, *a: setattr(self.state, "error",
                                                           "CLIENT ERROR 401: expired"))
    assert main(["field", "--cloud", "--out", str(out), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert "401" in err and err.count("\n") == 1 and "s3cr3t" not in err


_PLANT = 'name = "{name}"\nx = {x}\ny = 0.75\nheight = {height}\nradius = {radius}\n'


def _bed(tmp_path, *plants: dict):
    return _toml(tmp_path, "".join("[[plant]]\n" + _PLANT.format(**{
        "height": 0.2, "radius": 0.12, **plant}) for plant in plants))


@pytest.mark.parametrize("plants,words", [
    # Two plants at one spot, or 3 cm apart with 12 cm radii: each cloud holds the other's.
    ([{"name": "a", "x": 1.0}, {"name": "b", "x": 1.0}], ["'a' and 'b' overlap", "0 m apart"]),
    ([{"name": "a", "x": 1.0}, {"name": "b", "x": 1.03}], ["overlap", "need 0.28 m"]),
    ([{"name": "a", "x": 1.0, "height": -0.2}], ["height -0.2 m", "millimetres?"]),
    ([{"name": "a", "x": 1.0, "radius": -0.1}], ["radius -0.1 m"]),
    ([{"name": "a", "x": 1.0, "radius": 120}], ["radius 120 m", "millimetres?"]),
    ([{"name": "a", "x": 1.0, "height": 250}], ["height 250 m"]),
])
def test_a_bed_is_checked_as_a_whole_before_any_plan(tmp_path, plants, words):
    with pytest.raises(InputError) as refused:
        read_bed(_bed(tmp_path, *plants))
    for word in words:
        assert word in str(refused.value), str(refused.value)


def test_a_bed_of_too_many_plants_is_refused_before_reading_them_all(tmp_path):
    rows = "name,x,y\n" + "".join(f"p{k},{k * 0.001},0.5\n" for k in range(10_000))
    path = tmp_path / "bed.csv"
    path.write_text(rows)
    with pytest.raises(InputError, match="10,000 plants: a bed holds at most 500"):
        read_bed(path)


def test_the_simulated_and_the_physical_bed_refuse_the_same_bed(tmp_path, capsys):
    from flowerpose.cli import main

    path = _bed(tmp_path, {"name": "a", "x": 1.0, "radius": -0.1})
    for bot in (["--sim", "--dry-run"], ["--dry-run"]):
        assert main(["field", "--bed", str(path), *bot, "--out", str(tmp_path / "out")]) == 2
        assert "radius -0.1 m" in capsys.readouterr().err
