"""Inputs that are valid files but implausible data: each class refused in one line that
names the file, the problem and the fix (exit status 2, nothing written), or read with
what it assumed said in one line."""

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from flowerpose.cli import main
from flowerpose.cloudio import Cloud, read_cloud, write_cloud
from flowerpose.errors import InputError

RNG = np.random.default_rng(0)


def _ply(path: Path, points: np.ndarray, colours: np.ndarray, coordinate: str = "float",
         colour_names=("red", "green", "blue")) -> Path:
    """A binary PLY with the coordinates as `coordinate` ("float" or "double") and the
    colours under `colour_names`."""
    kind = "<f4" if coordinate == "float" else "<f8"
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              + "".join(f"property {coordinate} {a}\n" for a in "xyz")
              + "".join(f"property uchar {c}\n" for c in colour_names) + "end_header\n")
    rows = np.zeros(len(points), [("x", kind), ("y", kind), ("z", kind), ("r", "u1"),
                                  ("g", "u1"), ("b", "u1")])
    rows["x"], rows["y"], rows["z"] = points.T
    rows["r"], rows["g"], rows["b"] = colours.T
    path.write_bytes(header.encode() + rows.tobytes())
    return path


def _one_line(capsys, *words) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("flowerpose: error:"), err
    assert all(w in err for w in words), err
    return err


POINTS = RNG.uniform(-0.15, 0.15, (3000, 3))
COLOURS = RNG.integers(0, 256, (3000, 3)).astype(np.uint8)


def test_32_bit_coordinates_far_from_the_origin_are_refused(tmp_path, capsys):
    utm = _ply(tmp_path / "utm.ply", POINTS + [500_000.0, 4_000_000.0, 0.0], COLOURS)
    out = tmp_path / "out"
    assert main(["detect", str(utm), "--out", str(out), "--units", "m"]) == 2
    _one_line(capsys, str(utm), "32-bit", "steps of 250 mm", "doubles")
    assert not out.exists()
    # the same cloud stored as doubles keeps its millimetres
    doubles = _ply(tmp_path / "doubles.ply", POINTS + [500_000.0, 4_000_000.0, 0.0], COLOURS,
                   "double")
    assert len(np.unique(read_cloud(doubles, units="m").points, axis=0)) == len(POINTS)
    # and 32-bit floats near the origin are fine
    assert len(read_cloud(_ply(tmp_path / "near.ply", POINTS, COLOURS))) == len(POINTS)


def test_a_cloud_without_hue_is_refused(tmp_path, capsys):
    grey = _ply(tmp_path / "grey.ply", POINTS, np.repeat(COLOURS[:, :1], 3, axis=1))
    assert main(["detect", str(grey), "--out", str(tmp_path / "out")]) == 2
    _one_line(capsys, str(grey), "grey", "colours")
    assert not (tmp_path / "out").exists()


def test_colours_under_the_diffuse_names_are_read(tmp_path):
    named = _ply(tmp_path / "diffuse.ply", POINTS, COLOURS, "double",
                 ("diffuse_red", "diffuse_green", "diffuse_blue"))
    cloud = read_cloud(named)
    assert np.array_equal(cloud.colors, COLOURS) and np.allclose(cloud.points, POINTS)
    assert named.read_bytes().startswith(b"ply")  # read through a copy: the file untouched


def _cuboid(name: str, label: str, roll=0.1, pitch=0.2, yaw=0.3, x=0.0) -> dict:
    return {"objectName": name, "label": label, "centerX": x, "centerY": 0.0, "centerZ": 7.5,
            "roll": roll, "pitch": pitch, "yaw": yaw, "length": 1, "width": 1, "height": 1}


def _sagemaker(path: Path, cuboids: list[dict]) -> Path:
    path.write_text(json.dumps({"answers": [{"answerContent": {"boundingCuboids": {
        "boundingCuboids": cuboids}}}]}))
    return path


def test_label_angles_in_degrees_are_refused(tmp_path):
    from flowerpose.eval.scoring.truth import read_sagemaker_truth

    labels = _sagemaker(tmp_path / "labels.json", [_cuboid("Flower:1", "Flower"),
                                                   _cuboid("Flower:2", "Flower", 12, 126, 40)])
    with pytest.raises(InputError, match="beyond a rotation's range in radians") as error:
        read_sagemaker_truth(labels)
    assert "Flower:2" in str(error.value) and "math.radians" in str(error.value)


def test_cuboids_of_other_categories_are_left_out_and_named(tmp_path, caplog):
    from flowerpose.eval.scoring.truth import read_sagemaker_truth

    labels = _sagemaker(tmp_path / "labels.json", [
        _cuboid("Flower:1", "Flower"), _cuboid("Bud:1", "Bud", x=3.0),
        _cuboid("Bud:2", "Bud", x=6.0), _cuboid("Flower:2", "Flower", x=9.0)])
    with caplog.at_level(logging.WARNING, logger="flowerpose"):
        truth = read_sagemaker_truth(labels)
    assert [t.id for t in truth] == ["Flower:1", "Flower:2"]
    assert "2 Flower cuboids scored; left out 2 labelled Bud" in caplog.text
    only_buds = _sagemaker(tmp_path / "buds.json", [_cuboid("Bud:1", "Bud")])
    with pytest.raises(InputError, match=r"no cuboid is labelled Flower \(labels: Bud \(1\)\)"):
        read_sagemaker_truth(only_buds)


def test_an_unlabelled_flower_at_a_labelled_ones_centre_is_refused(tmp_path, capsys):
    import sys

    sys.path.insert(0, str(Path(__file__).parent / "eval"))
    from realplants import CENTRES, SCALE, write_real_plant

    folder = write_real_plant(tmp_path / "plant", "cloud", source={
        "unlabelled": [(CENTRES[2] * SCALE + 0.001).tolist()]})
    assert main(["eval", "-q", "--source", "real", str(folder), "--out",
                 str(tmp_path / "run")]) == 2
    _one_line(capsys, str(folder / "source.json"), "labelled or unlabelled, not both")


def test_scoring_against_truth_that_does_not_overlap_is_refused(tmp_path, capsys):
    flowers = tmp_path / "flowers.json"
    flowers.write_text(json.dumps({"units": "m", "flowers": [
        {"id": 0, "center": [0.0, 0.0, 0.3], "normals": {"plane": [0, 0, 1]}}]}))
    truth = tmp_path / "plant.json"
    truth.write_text(json.dumps({"flowers": [
        {"id": 0, "center": [1.5, 0.75, 0.3], "normal": [0, 0, 1]}]}))
    assert main(["score", str(flowers), str(truth)]) == 2
    _one_line(capsys, str(flowers), "do not overlap", "another plant's truth")


def test_a_grid_the_machine_cannot_hold_is_refused_before_it_is_made():
    from flowerpose.pipeline.grid import GridConfig, project, view_directions

    cloud = Cloud(np.array([[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]), np.zeros((2, 3), np.uint8))
    config = GridConfig(pixel_size_m=2e-5, max_image_px=100_000)
    with pytest.raises(InputError, match="grid.pixel_size_m") as error:
        project(cloud, view_directions(6)[0], config)
    assert "GB" in str(error.value)


def test_an_output_folder_that_takes_no_file_is_refused_before_any_work(tmp_path, capsys,
                                                                        monkeypatch):
    from flowerpose import outputs

    cloud = write_cloud(tmp_path / "cloud.ply", Cloud(POINTS, COLOURS))

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(outputs, "temporary_beside", refuse)
    assert main(["detect", str(cloud), "--out", str(tmp_path / "out")]) == 2
    _one_line(capsys, str(tmp_path / "out"), "cannot write into", "Permission denied")


@pytest.mark.parametrize("command", [
    ["bench", "--points", "1000"], ["plant", "--seed", "1"], ["scan", "--sim", "--plant", "p"],
    ["field", "--sim", "--bed", "bed.toml"], ["frames", "scan"], ["reconstruct", "frames"],
    ["dataset", "--plants", "2"], ["sweep", "--grid", "grid.pixel_size_m=0.001,0.002"],
    ["stress"], ["eval"], ["guard"]])
def test_every_command_tries_its_output_folder_before_any_work(tmp_path, capsys, monkeypatch,
                                                                command):
    from flowerpose import outputs

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(outputs, "temporary_beside", refuse)
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    assert main([*command, "--out", str(out)]) == 2
    _one_line(capsys, str(out), "cannot write into", "Permission denied")
    assert not out.exists()


def test_what_a_run_assumed_is_stated_in_its_reports(tmp_path, capsys):
    """A warned assumption reaches the files: the cloud's unit in flowers.json's notes, the
    labels left out in the score's report.json and report.md beside the detection's."""
    millimetres = _ply(tmp_path / "mm.ply", POINTS * 1000.0, COLOURS, "double")
    assert main(["detect", "-q", str(millimetres), "--out", str(tmp_path / "detect")]) == 0
    notes = json.loads((tmp_path / "detect" / "flowers.json").read_text())["notes"]
    assert any("millimetres" in note for note in notes), notes

    flowers = tmp_path / "flowers.json"
    flowers.write_text(json.dumps({"units": "m", "notes": ["detect: an assumption"],
                                   "flowers": [{"id": 0, "center": [0.0, 0.0, 0.3],
                                                "normals": {"plane": [0, 0, 1]}}]}))
    labels = _sagemaker(tmp_path / "labels.json", [
        _cuboid("Flower:1", "Flower"), _cuboid("Bud:1", "Bud", x=3.0)])
    out = tmp_path / "score"
    assert main(["score", "-q", str(flowers), str(labels), "--truth-format", "sagemaker",
                 "--out", str(out)]) == 0
    plant = json.loads((out / "report.json").read_text())["plants"][0]
    assert plant["notes"][0] == "detect: an assumption"
    assert "left out 1 labelled Bud" in plant["notes"][1]
    markdown = (out / "report.md").read_text()
    assert "## What the run assumed" in markdown and "left out 1 labelled Bud" in markdown


def test_a_stage_from_the_cache_says_what_it_assumed_again(tmp_path, caplog):
    from flowerpose.cache import StageCache
    from flowerpose.log import LOG, noted

    def compute() -> dict:
        LOG.warning("note: assumed metres")
        return {"value": 1}

    cache = StageCache(tmp_path / "cache")
    for fresh in (True, False):
        with noted() as notes:
            result, cached, _ = cache.run("stage", {}, [], tmp_path, (), compute)
        assert result == {"value": 1} and cached is not fresh
        assert notes == ["note: assumed metres"]


def _pcd(path: Path, points: np.ndarray, colours: np.ndarray, size: int) -> Path:
    """A binary PCD with coordinates of `size` bytes (4: float32, as Open3D and PCL write
    them; 8: doubles) and packed RGB."""
    kind = f"<f{size}"
    rows = np.zeros(len(points), [("x", kind), ("y", kind), ("z", kind), ("rgb", "<u4")])
    rows["x"], rows["y"], rows["z"] = points.T
    rows["rgb"] = (colours[:, 0].astype(np.uint32) << 16 | colours[:, 1].astype(np.uint32) << 8
                   | colours[:, 2].astype(np.uint32))
    path.write_bytes(
        b"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE %d %d %d 4\nTYPE F F F U\n"
        b"COUNT 1 1 1 1\nWIDTH %d\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS %d\n"
        b"DATA binary\n" % (size, size, size, len(points), len(points)) + rows.tobytes())
    return path


def test_32_bit_pcd_coordinates_far_from_the_origin_are_refused(tmp_path, capsys):
    far = POINTS + [500_000.0, 4_000_000.0, 0.0]
    singles = _pcd(tmp_path / "singles.pcd", far, COLOURS, 4)
    assert main(["detect", str(singles), "--out", str(tmp_path / "out"), "--units", "m"]) == 2
    _one_line(capsys, str(singles), "32-bit", "steps of 250 mm", "doubles")
    assert not (tmp_path / "out").exists()
    near = read_cloud(_pcd(tmp_path / "near.pcd", POINTS, COLOURS, 4))
    assert np.allclose(near.points, POINTS, atol=1e-7) and np.array_equal(near.colors, COLOURS)
    # Open3D reads 64-bit PCD coordinates as zeros: refused, not read as one point
    doubles = _pcd(tmp_path / "doubles.pcd", far, COLOURS, 8)
    with pytest.raises(InputError, match="64-bit.*reads as zeros.*PLY"):
        read_cloud(doubles, units="m")


def test_a_camera_image_opengl_cannot_render_is_refused_before_any_work(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["eval", "--set", "scan.camera.width=20000", "--out", str(out)]) == 2
    _one_line(capsys, "scan.camera.width", "at most 16384 pixels")
    assert not out.exists()
