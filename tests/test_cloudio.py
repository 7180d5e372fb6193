import numpy as np
import pytest

from flowerpose.cloudio import Cloud, read_cloud, write_cloud
from flowerpose.errors import InputError

RNG = np.random.default_rng(0)


def _write(path, points, colors=True):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, float)))
    if colors:
        pcd.colors = o3d.utility.Vector3dVector(np.full((len(points), 3), 0.5))
    o3d.io.write_point_cloud(str(path), pcd)
    return path


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    cloud = Cloud(rng.random((50, 3)), rng.integers(0, 256, (50, 3)).astype(np.uint8))
    back = read_cloud(write_cloud(tmp_path / "c.ply", cloud))
    np.testing.assert_array_equal(back.points, cloud.points)
    np.testing.assert_array_equal(back.colors, cloud.colors)


def test_millimetres_are_recognised_and_converted(tmp_path, capsys):
    points = np.random.default_rng(1).random((100, 3)) * 400.0
    cloud = read_cloud(_write(tmp_path / "mm.ply", points))
    np.testing.assert_allclose(cloud.points, points / 1000)
    assert "millimetres" in capsys.readouterr().err


@pytest.mark.parametrize("problem, make", [
    ("file not found", lambda d: d / "missing.ply"),
    ("no colours", lambda d: _write(d / "grey.ply", RNG.random((10, 3)), colors=False)),
    ("NaN", lambda d: _write(d / "nan.ply", np.r_[RNG.random((9, 3)), [[np.nan, 0, 0]]])),
    ("fits neither", lambda d: _write(d / "huge.ply", RNG.random((10, 3)) * 40)),
    ("not a PLY", lambda d: (d / "text.ply").write_text("hello") and d / "text.ply"),
    ("expected a .ply", lambda d: (d / "c.txt").write_text("1 2 3") and d / "c.txt"),
])
def test_bad_clouds_are_refused_with_the_file_named(tmp_path, problem, make):
    path = make(tmp_path)
    with pytest.raises(InputError, match=problem) as err:
        read_cloud(path)
    assert str(path) in str(err.value)


def test_empty_cloud(tmp_path):
    path = tmp_path / "empty.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n")
    with pytest.raises(InputError, match="no points"):
        read_cloud(path)
    assert len(read_cloud(path, allow_empty=True)) == 0


def test_a_truncated_ply_is_refused_not_padded_with_zeros(tmp_path):
    path = write_cloud(tmp_path / "c.ply", Cloud(RNG.random((500, 3)), np.full((500, 3), 200,
                                                                               np.uint8)))
    data = path.read_bytes()
    path.write_bytes(data[:len(data) - 27 * 200])
    with pytest.raises(InputError, match="truncated: the header declares 500 points, the "
                                         "file holds 300"):
        read_cloud(path)


def test_colours_stored_as_floats_are_read_as_colours(tmp_path):
    colours = RNG.random((20, 3)).astype(np.float32)
    rows = np.zeros(20, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "<f4"),
                               ("green", "<f4"), ("blue", "<f4")])
    rows["x"], rows["y"], rows["z"] = RNG.random((20, 3)).T
    rows["red"], rows["green"], rows["blue"] = colours.T
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 20\n"
              + "".join(f"property {t} {n}\n" for t, n in (
                  ("double", "x"), ("double", "y"), ("double", "z"), ("float", "red"),
                  ("float", "green"), ("float", "blue"))) + "end_header\n")
    path = tmp_path / "float.ply"
    path.write_bytes(header.encode() + rows.tobytes())
    np.testing.assert_allclose(read_cloud(path).colors, np.round(colours * 255), atol=1)


def test_a_unit_the_extent_contradicts_is_refused(tmp_path):
    metres = _write(tmp_path / "m.ply", RNG.random((50, 3)) * 0.4)
    with pytest.raises(InputError, match="mm in millimetres: not a plant"):
        read_cloud(metres, units="mm")
    millimetres = _write(tmp_path / "mm.ply", RNG.random((50, 3)) * 400.0)
    with pytest.raises(InputError, match="in metres: not a plant"):
        read_cloud(millimetres, units="m")


_ASCII_HEADER = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                 "property float z\nproperty uchar red\nproperty uchar green\n"
                 "property uchar blue\nend_header\n")


@pytest.mark.parametrize("name, text, problem", [
    # Open3D would return the first point alone, and RPly print its complaint.
    ("letter.ply", _ASCII_HEADER + "0 0 0 1 2 3\n1 1 x 1 2 3\n",
     "cannot be read: error reading 'z' of 'vertex' number 1"),
    ("noformat.ply", "ply\nelement vertex 1\nend_header\n", "cannot be read: invalid file format"),
    ("garbage.pcd", "not a pcd\n", "cannot be read: unable to parse header"),
])
def test_what_open3d_and_rply_say_of_a_bad_file_is_one_line_of_ours(tmp_path, capfd, name, text,
                                                                   problem):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError, match=problem) as err:
        read_cloud(path)
    assert str(err.value).startswith(str(path))
    assert capfd.readouterr() == ("", "")  # nothing in their words, on either stream


def test_an_empty_cloud_is_written_as_a_ply_of_no_points(tmp_path, capfd):
    path = write_cloud(tmp_path / "none.ply", Cloud(np.zeros((0, 3)), np.zeros((0, 3), np.uint8)))
    assert len(read_cloud(path, allow_empty=True)) == 0
    assert capfd.readouterr() == ("", "")
