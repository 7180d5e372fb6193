"""Inputs that disagree with themselves are read right or refused in one line, never
scored as if they were right (issue: no silent wrong answers)."""

import json

import numpy as np
import pytest

from flowerpose.cli import main
from flowerpose.cloudio import read_cloud

HEADER = ("ply\nformat ascii 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
          "property float z\nproperty {t} red\nproperty {t} green\nproperty {t} blue\n"
          "end_header\n")


def _ascii_ply(path, points, colours, declared=None, colour_type="uchar"):
    rows = "".join(f"{p[0]} {p[1]} {p[2]} {c[0]} {c[1]} {c[2]}\n"
                   for p, c in zip(points, colours, strict=True))
    path.write_text(HEADER.format(n=len(points) if declared is None else declared,
                                  t=colour_type) + rows)
    return path


def test_a_header_that_declares_fewer_or_more_points_than_the_body_is_refused(tmp_path, capsys):
    points = np.random.default_rng(0).uniform(0, 0.2, (30, 3))
    colours = np.full((30, 3), 200)
    for declared in (10, 40):
        path = _ascii_ply(tmp_path / f"c{declared}.ply", points, colours, declared)
        assert main(["detect", str(path), "--out", str(tmp_path / f"out{declared}")]) == 2
        err = capsys.readouterr().err
        said = "header and body disagree" if declared < 30 else "unexpected end of file"
        assert said in err and path.name in err and err.count("\n") == 1
    binary = tmp_path / "binary.ply"
    from flowerpose.cloudio import Cloud, write_cloud

    write_cloud(binary, Cloud(points, colours.astype(np.uint8)))
    with open(binary, "ab") as handle:  # a body longer than its header says
        handle.write(binary.read_bytes()[-15 * 5:])
    with pytest.raises(Exception, match="header and body disagree"):
        read_cloud(binary)


def test_16_bit_colours_are_read_as_16_bit_and_other_types_refused(tmp_path):
    points = np.zeros((2, 3)) + [[0, 0, 0], [0.1, 0, 0]]
    wide = read_cloud(_ascii_ply(tmp_path / "u16.ply", points, [[65535, 32896, 0], [257, 0, 0]],
                                 colour_type="ushort"))
    assert wide.colors.tolist() == [[255, 128, 0], [1, 0, 0]]
    with pytest.raises(Exception, match="colours of type int"):
        read_cloud(_ascii_ply(tmp_path / "int.ply", points, [[1, 2, 3], [4, 5, 6]],
                              colour_type="int"))


def test_flowers_json_in_millimetres_is_scored_in_metres(tmp_path, capsys):
    truth = {"units": "m", "flowers": [{"id": 0, "center": [0.1, 0.2, 0.3],
                                        "normal": [0, 0, 1]}]}
    (tmp_path / "plant.json").write_text(json.dumps(truth))
    for units, centre in (("m", [0.1, 0.2, 0.3]), ("mm", [100.0, 200.0, 300.0])):
        flowers = {"units": units, "flowers": [{"id": 0, "center": centre, "normals": {
            "plane": [0, 0, 1], "superellipsoid": None, "paraboloid": None}}]}
        (tmp_path / f"{units}.json").write_text(json.dumps(flowers))
        assert main(["score", str(tmp_path / f"{units}.json"), str(tmp_path / "plant.json"),
                     "--out", str(tmp_path / f"score-{units}")]) == 0
        report = json.loads((tmp_path / f"score-{units}" / "report.json").read_text())
        assert report["summary"]["found"] == 1 and report["summary"]["fp"] == 0
    (tmp_path / "ft.json").write_text(json.dumps({"units": "ft", "flowers": []}))
    assert main(["score", str(tmp_path / "ft.json"), str(tmp_path / "plant.json")]) == 2
    assert '"units" must be "m" or "mm"' in capsys.readouterr().err


def test_labels_given_twice_are_refused_and_touching_ones_stay(tmp_path, capsys):
    from realplants import cuboids, write_real_plant

    folder = write_real_plant(tmp_path / "plant", "candidates")
    labels = json.loads((folder / "labels.json").read_text())
    found = labels["answers"][0]["answerContent"]["boundingCuboids"]["boundingCuboids"]
    found.append(dict(found[0], objectName="Flower:9"))
    (folder / "labels.json").write_text(json.dumps(labels))
    assert main(["eval", "--source", "real", str(folder), "--out", str(tmp_path / "o")]) == 2
    assert "are the same cuboid" in capsys.readouterr().err
    # Two labels close together (touching flowers) are two flowers.
    found[-1]["centerX"] += 0.2
    (folder / "labels.json").write_text(json.dumps(labels))
    assert main(["eval", "--source", "real", str(folder), "--out", str(tmp_path / "p")]) == 0
    assert cuboids  # the helper the labels come from


@pytest.mark.slow
def test_repeated_ids_a_folder_twice_and_folders_named_alike(tmp_path, capsys):
    from realplants import write_real_plant

    truth = {"flowers": [{"id": 3, "center": [0, 0, 0], "normal": [0, 0, 1]},
                         {"id": 3, "center": [0.1, 0, 0], "normal": [0, 0, 1]}]}
    (tmp_path / "plant.json").write_text(json.dumps(truth))
    (tmp_path / "f.json").write_text(json.dumps({"units": "m", "flowers": []}))
    assert main(["score", str(tmp_path / "f.json"), str(tmp_path / "plant.json")]) == 2
    assert "flower id 3 is given 2 times" in capsys.readouterr().err
    a = write_real_plant(tmp_path / "a" / "plant", "candidates")
    b = write_real_plant(tmp_path / "b" / "plant", "candidates", seed=1)
    assert main(["eval", "--source", "real", str(a), str(a), "--out", str(tmp_path / "o")]) == 2
    assert "is given twice" in capsys.readouterr().err
    assert main(["eval", "--source", "real", str(a), str(b), "--out", str(tmp_path / "n")]) == 0
    report = json.loads((tmp_path / "n" / "report.json").read_text())
    assert [p["plant"] for p in report["plants"]] == ["a-plant", "b-plant"]
