"""Every file the project writes, it reads back the same: flowers.json through the detection
and its reader (the unit stated once, applied once), labels.json through `write_labels`
(the label server's writer; its own round trip is in tests/eval/test_label_server.py), the
guard's accepted decisions, report.json and a generated plant's plant.json."""

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent / "eval"))
from realplants import CENTRES, NORMALS, write_real_plant  # noqa: E402

from flowerpose.cloudio import read_cloud  # noqa: E402
from flowerpose.eval.reports.report import build_report, write_report  # noqa: E402
from flowerpose.eval.scoring.labels import Label, LabelFile, read_labels, write_labels  # noqa: E402
from flowerpose.eval.studies import accepted  # noqa: E402
from flowerpose.eval.studies.fresh_seeds import FRESH_SEEDS  # noqa: E402
from flowerpose.pipeline.flowers import find_flowers, read_flowers, write_flowers  # noqa: E402


def test_flowers_json_reads_back_as_detected_in_metres(tmp_path):
    folder = write_real_plant(tmp_path / "plant", "cloud")
    result = find_flowers(read_cloud(folder / "cloud.ply"))
    assert result.flowers
    write_flowers(tmp_path / "flowers.json", result, folder / "cloud.ply")
    again = read_flowers(tmp_path / "flowers.json")
    assert len(again) == len(result.flowers)
    for flower, entry in zip(result.flowers, again, strict=True):
        assert np.allclose(entry["center"], flower.pose.center)
        for method, normal in flower.pose.normals.items():
            assert (normal is None) == (entry["normals"][method] is None)
            if normal is not None:
                assert np.allclose(entry["normals"][method], normal)
    # Written again from what was read, the file is the same: nothing scaled twice.
    document = json.loads((tmp_path / "flowers.json").read_text())
    assert document["units"] == "m"


def test_labels_read_back_as_written(tmp_path):
    labels = LabelFile([Label(f"F{k}", c * 2.0, n, "labelled", "ana", "2026-12-06T10:00:00+00:00")
                        for k, (c, n) in enumerate(zip(CENTRES, NORMALS, strict=True))]
                       + [Label("U", CENTRES[0] * 2.0, None, "unlabelled")],
                       truth_scale=2.0, sessions=[{"labeller": "ana", "seconds": 12}])
    write_labels(tmp_path / "labels.json", labels)
    again = read_labels(tmp_path / "labels.json")
    assert again.truth_scale == 2.0 and again.sessions == labels.sessions
    assert [(f.id, f.state, f.labeller, f.time) for f in again.flowers] == [
        (f.id, f.state, f.labeller, f.time) for f in labels.flowers]
    assert np.allclose([f.center for f in again.flowers], [f.center for f in labels.flowers])
    assert np.allclose([f.normal for f in again.flowers[:-1]], NORMALS)
    # Written again from what was read, it reads the same again: nothing scaled twice.
    write_labels(tmp_path / "again.json", again)
    twice = read_labels(tmp_path / "again.json")
    assert twice.truth_scale == 2.0
    assert np.allclose([f.center for f in twice.flowers], [f.center for f in labels.flowers])


def test_the_accepted_decisions_read_back_as_appended(tmp_path):
    record = {"entry": "oracle-20", "battery_version": 2, "commit": "abc", "base": "def",
              "date": "2026-12-06T10:00:00+00:00", "command": "flowerpose guard --accept",
              "settings": [{"cluster.eps": 0.009}], "run_seed": 7, "decision": "loss",
              "reason": "a trade", "measures": {"plane": {"loss": 0.2, "se": 0.1}},
              "plants": {"seeds": [FRESH_SEEDS.start + 1, FRESH_SEEDS.start + 20]}}
    accepted.append(tmp_path / "accepted.json", [], [record])
    assert accepted.read_history(tmp_path / "accepted.json") == [record]


def test_report_json_reads_back_as_built(tmp_path):
    plants = [{"plant": "p", "gt": 2, "visible": 2, "detections": 2, "found": 2,
               "found_visible": 2, "extra": 0, "fp": 0,
               "error_deg": dict.fromkeys(("plane", "superellipsoid", "paraboloid"), [1.5, 3.0]),
               "failed": dict.fromkeys(("plane", "superellipsoid", "paraboloid"), 0),
               "matches": []}]
    report = build_report({"source": "real"}, plants, {"total": 1.0})
    write_report(tmp_path, report, "a report")
    assert json.loads((tmp_path / "report.json").read_text()) == json.loads(json.dumps(report))


def test_a_generated_plants_truth_reads_back_as_made(tmp_path):
    from flowerpose.eval.scoring.truth import read_plant_truth
    from flowerpose.sim.bundle import make_plant

    bundle = make_plant(3, "easy", points=2000, out_dir=tmp_path)
    truth = {str(t.id): t for t in read_plant_truth(tmp_path / "plant.json")}
    for flower in bundle.plant.flowers:
        assert np.allclose(truth[str(flower.id)].center, flower.center)
        assert np.allclose(truth[str(flower.id)].normal, flower.normal)
