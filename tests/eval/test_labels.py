"""The project's own label file (what a labeller saves) and `flowerpose agree`: a save keeps
the file it replaces, a real plant folder reads it as it reads the others, and the
agreement of two labellings is measured as written."""

import json

import numpy as np
import pytest
from realplants import CENTRES, NORMALS, write_real_plant
from scipy.spatial.transform import Rotation

from flowerpose.cli import main
from flowerpose.errors import InputError
from flowerpose.eval.labelling.agreement import agreement, read_labelling
from flowerpose.eval.scoring.labels import Label, LabelFile, read_labels, write_labels
from flowerpose.eval.scoring.real_source import read_real_plant, real_truth


def _labels(normals=NORMALS, states=None, scale=1.0) -> LabelFile:
    states = states or ["labelled"] * len(CENTRES)
    return LabelFile([Label(f"F{k}", c * scale, n if s == "labelled" else None, s, "test",
                            "2026-12-05T10:00:00+00:00")
                      for k, (c, n, s) in enumerate(zip(CENTRES, normals, states, strict=True))],
                     truth_scale=scale)


def test_a_save_round_trips_and_keeps_every_earlier_file(tmp_path):
    path = tmp_path / "labels.json"
    first = _labels(states=["labelled", "unlabelled", "rejected", "labelled"])
    assert write_labels(path, first) is None
    again = read_labels(path)
    assert [f.state for f in again.flowers] == ["labelled", "unlabelled", "rejected", "labelled"]
    assert np.allclose(again.flowers[0].normal, NORMALS[0])
    assert again.flowers[1].normal is None and len(again.labelled()) == 2
    assert np.allclose(again.unlabelled(), CENTRES[1:2])
    saved = path.read_bytes()
    assert write_labels(path, _labels()) == tmp_path / "labels.json.1.bak"
    assert write_labels(path, _labels()) == tmp_path / "labels.json.2.bak"
    assert (tmp_path / "labels.json.1.bak").read_bytes() == saved


@pytest.mark.parametrize("flower, problem", [
    ({"center": [0, 0, 0], "state": "labelled"}, 'needs a "normal"'),
    ({"center": [0, 0, 0], "normal": [0, 0, 1], "state": "maybe"}, '"state" must be one of'),
    ({"center": [0, 0], "normal": [0, 0, 1]}, '"center" must be 3 finite numbers'),
    ({"center": [0, 0, 0], "normal": [0, 0, 0]}, "zero vector"),
])
def test_a_malformed_flower_is_named(tmp_path, flower, problem):
    path = tmp_path / "labels.json"
    path.write_text(json.dumps({"format": "flowerpose-labels", "version": 1,
                                "flowers": [flower]}))
    with pytest.raises(InputError, match=problem) as error:
        read_labels(path)
    assert str(path) in str(error.value) and "flower 0" in str(error.value)


def test_a_real_plant_folder_reads_the_label_file(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "cloud")
    (folder / "labels.json").unlink()
    write_labels(folder / "labels.json",
                 _labels(states=["labelled", "labelled", "labelled", "unlabelled"], scale=2.0))
    plant = read_real_plant(folder)
    assert plant.label_format == "flowerpose" and plant.truth_scale == 2.0
    truth = real_truth(plant)
    labelled = [t for t in truth if not str(t.id).startswith("unlabelled")]
    assert [t.id for t in labelled] == ["F0", "F1", "F2"]
    assert np.allclose([t.center for t in labelled], CENTRES[:3])  # divided by the scale
    extra = [t for t in truth if str(t.id).startswith("unlabelled")]
    assert len(extra) == 1 and np.allclose(extra[0].center, CENTRES[3])
    assert not extra[0].visible  # a detection on it counts as extra


def test_a_labelling_agrees_with_itself_and_a_turned_one_by_the_turn(tmp_path, capsys):
    write_labels(tmp_path / "a.json", _labels())
    # each normal turned by 10 degrees about an axis at right angles to it
    axes = np.cross(NORMALS, [[0.3, 0.5, 0.8]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    turned = np.array([Rotation.from_rotvec(np.radians(10.0) * a).apply(n)
                       for a, n in zip(axes, NORMALS, strict=True)])
    states = ["labelled", "labelled", "labelled", "unlabelled"]
    write_labels(tmp_path / "b.json", _labels(turned, states))
    a = read_labelling(tmp_path / "a.json")
    same = agreement(a, a)
    assert same["matched"] == 4 and same["angle_deg"]["mean"] == 0.0
    assert same["only_a"] == same["only_b"] == []
    other = agreement(a, read_labelling(tmp_path / "b.json"))
    assert other["angle_deg"]["n"] == 3
    assert other["angle_deg"]["mean"] == pytest.approx(10.0, abs=1e-3)
    assert [(r["a"], r["b"]) for r in other["pose_in_one"]] == [("F3", "F3")]
    assert main(["agree", str(tmp_path / "a.json"), str(tmp_path / "b.json")]) == 0
    said = capsys.readouterr().out
    assert "on 3 flowers: mean 10.0°" in said and "median 10.0°" in said


def test_flowers_only_one_labelling_holds_are_named(tmp_path):
    write_labels(tmp_path / "a.json", _labels())
    fewer = _labels()
    fewer.flowers = fewer.flowers[:2]
    write_labels(tmp_path / "b.json", fewer)
    result = agreement(read_labelling(tmp_path / "a.json"), read_labelling(tmp_path / "b.json"))
    assert result["matched"] == 2 and result["only_a"] == ["F2", "F3"] and result["only_b"] == []


def test_agree_compares_sagemaker_cuboids_with_a_label_file(tmp_path, capsys):
    folder = write_real_plant(tmp_path / "plant", "cloud")
    write_labels(tmp_path / "mine.json", _labels())
    assert main(["agree", str(folder / "labels.json"), str(tmp_path / "mine.json"),
                 "--json", str(tmp_path / "agree.json")]) == 0
    said = capsys.readouterr().out
    assert "matched within 20 mm: 4" in said and "on 4 flowers: mean 0.0°" in said
    assert json.loads((tmp_path / "agree.json").read_text())["angle_deg"]["n"] == 4


def test_agree_refuses_what_is_not_a_labelling_in_one_line(tmp_path, capsys):
    (tmp_path / "x.json").write_text('{"x": 1}')
    write_labels(tmp_path / "mine.json", _labels())
    assert main(["agree", str(tmp_path / "x.json"), str(tmp_path / "mine.json")]) == 2
    err = capsys.readouterr().err.strip()
    assert str(tmp_path / "x.json") in err and "not a label file" in err
    assert err.count("\n") == 0


def test_agree_matches_within_metres_whatever_the_clouds_unit(tmp_path, capsys):
    """Two labellings of a millimetre cloud 1 mm apart match within the default 2 cm."""
    folder = write_real_plant(tmp_path / "plant", "cloud", source={"units": "mm"})
    (folder / "labels.json").unlink()
    millimetres = _labels()
    for flower in millimetres.flowers:
        flower.center = flower.center * 1000
    write_labels(folder / "labels.json", millimetres)
    moved = _labels()
    for flower in moved.flowers:
        flower.center = flower.center * 1000 + [1.0, 0.0, 0.0]
    write_labels(folder / "second.json", moved)
    assert main(["agree", str(folder / "labels.json"), str(folder / "second.json")]) == 0
    assert "matched within 20 mm: 4" in capsys.readouterr().out
    # The unit given, or told by the folder's cloud, says the same.
    assert main(["agree", str(folder / "labels.json"), str(folder / "second.json"),
                 "--units", "mm"]) == 0
    assert "matched within 20 mm: 4" in capsys.readouterr().out
