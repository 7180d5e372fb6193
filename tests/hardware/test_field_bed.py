"""flowerpose field with the physical bot (--port, --cloud): a bed filmed plant after plant
by the serial backend on a virtual Farmduino with a fake USB camera, resumed, and the
refusals that come before anything moves."""

import functools

import pytest
from cli_run import run_cli
from cloud_fakes import FakeCapture

from flowerpose.hardware.backends import usb_camera
from flowerpose.jsonio import read_json
from flowerpose.scanio import frame_files, read_trajectory

#: Two plants 0.6 m apart on a short path: three columns, a ring and a dome ring each.
BED = """[scan]
pause_s = 0.05

[scan.path]
cylinder_radius_m = 0.3
azimuth_step_deg = 120.0
cylinder_bottom_m = 0.2
cylinder_step_m = 0.1
dome_polar_deg = [50.0]

[[plant]]
name = "near"
x = 1.0
y = 0.75
height = 0.22
radius = 0.08

[[plant]]
name = "far"
x = 1.6
y = 0.75
height = 0.22
radius = 0.08
"""
SMALL_CAMERA = ["--set", "scan.camera.width=64", "--set", "scan.camera.height=48"]



@pytest.fixture
def field(tmp_path, monkeypatch):
    """A fake camera at tmp_path/video0 (grey frames, 100 fps) and the bed file."""
    monkeypatch.setattr(usb_camera, "open_v4l2", lambda path: FakeCapture(fps=100.0))
    monkeypatch.setattr(usb_camera, "UsbCameraConfig", functools.partial(
        usb_camera.UsbCameraConfig, settle_s=0.0))
    (tmp_path / "video0").write_text("")
    (tmp_path / "bed.toml").write_text(BED)
    monkeypatch.setenv("FLOWERPOSE_CACHE", str(tmp_path / "cache"))
    return tmp_path


@pytest.mark.slow
def test_a_bed_is_filmed_plant_after_plant_through_the_serial_backend(field, capsys):
    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    out = field / "bed"
    argv = ["field", "--bed", field / "bed.toml", "--camera", field / "video0", "--out", out,
            *SMALL_CAMERA, "--keep-going"]
    with virtual.VirtualFarmduino(time_scale=100.0,
                                  params=virtual.FEEDBACK_PARAMETERS) as device:
        code, said, err = run_cli(capsys, *argv, "--port", device.path)
    assert code == 0, err
    journal = read_json(out / "bed.json")
    first, second = journal["order"]
    assert {first, second} == {"near", "far"} and journal["bot"]["backend"] == "serial"
    assert "homing" in err and f"[1/2] {first}: filming" in said
    assert f"[2/2] {second}: filming" in said
    for name in ("near", "far"):
        scan = out / "plants" / name / "scan"
        manifest = read_json(scan / "scan.json")
        assert manifest["status"] == "complete" and manifest["completed"] == 6
        assert manifest["source"]["plant"]["at"] == [1.0 if name == "near" else 1.6, 0.75]
        # The frames chosen while recording: bins of this plant's own scan.
        assert manifest["source"]["camera"]["frames"].startswith("the 3 sharpest")
        trajectory = read_trajectory(scan / "trajectory.csv")
        assert len(trajectory) > 0 and trajectory.frame[-1] == len(frame_files(scan)) - 1
        # Grey frames hold nothing to reconstruct: the plant fails there, with its reason,
        # and the bed goes on (--keep-going).
        plant = journal["plants"][name]
        assert plant["stage"] == "failed" and plant["failed_at"] == "reconstruct"
        assert plant["error"] and plant["seconds"]["scan"] > 0
    assert journal["timing_s"]["filming"] > 0 and journal["status"] == "complete"
    report = read_json(out / "report.json")
    assert report["summary"]["plants"] == 2 and report["summary"]["failed"] == 2
    assert "near: failed at reconstruct" in (out / "report.md").read_text()
    assert (out / "report.html").is_file()

    # Rerun: nothing is filmed again (the failed plants stay failed).
    frames = {name: frame_files(out / "plants" / name / "scan") for name in ("near", "far")}
    with virtual.VirtualFarmduino(time_scale=100.0,
                                  params=virtual.FEEDBACK_PARAMETERS) as device:
        code, said, err = run_cli(capsys, *argv, "--port", device.path)
    assert code == 0, err
    assert "filming" not in said
    assert {n: frame_files(out / "plants" / n / "scan") for n in frames} == frames


@pytest.mark.slow
def test_a_camera_that_goes_silent_fails_its_plant_parks_the_head_and_the_bed_goes_on(
        field, capsys, monkeypatch):
    """The camera stops delivering frames in the first plant's scan: that plant fails
    with the camera's reason, the head is lifted to the top of Z where the gantry stands,
    and with --keep-going the next plant is tried (and fails the same way, the camera
    being gone); without it the bed stops at the first, exit 2."""
    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    monkeypatch.setattr(usb_camera, "open_v4l2", lambda path: FakeCapture(fps=100.0,
                                                                          frames=150))
    monkeypatch.setattr(usb_camera, "UsbCameraConfig", functools.partial(
        usb_camera.UsbCameraConfig, settle_s=0.0, frame_timeout_s=0.3))
    argv = ["field", "--bed", field / "bed.toml", "--camera", field / "video0",
            *SMALL_CAMERA]
    for extra, code_wanted in ((["--keep-going"], 0), ([], 2)):
        out = field / f"bed{len(extra)}"
        with virtual.VirtualFarmduino(time_scale=100.0,
                                      params=virtual.FEEDBACK_PARAMETERS) as device:
            code, said, err = run_cli(capsys, *argv, "--out", out, *extra, "--port",
                                      device.path)
            moves = [line for line in device.received if line.startswith("G00")]
        assert code == code_wanted, err
        journal = read_json(out / "bed.json")
        first = journal["plants"][journal["order"][0]]
        assert first["stage"] == "failed" and first["failed_at"] == "scan", first
        assert "camera" in first["error"] or "frames" in first["error"], first["error"]
        # Parked: the last move lifts the head to the top of Z (FarmBot's z = 0).
        assert float(moves[-1].split("Z")[1].split()[0]) == 0.0, moves[-3:]
        second = journal["plants"][journal["order"][1]]
        assert second["stage"] == ("failed" if extra else "planned"), second
    assert "Traceback" not in err and len(err.strip().splitlines()[-1:]) == 1


def test_the_physical_bed_is_planned_before_anything_opens(field, capsys):
    far = BED.replace("x = 1.6", "x = 9.0")
    (field / "far.toml").write_text(far)
    code, _, err = run_cli(capsys, "field", "--bed", field / "far.toml", "--port", "/dev/none",
                        "--camera", field / "video0", "--out", field / "bed")
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "far" in lines[0], err
    assert not (field / "bed").exists()


@pytest.mark.parametrize("argv, words", [
    (["--camera", "{tmp}/video0"], ["choose the bot", "--port", "--cloud"]),
    (["--port", "/dev/none"], ["--camera", "needed"]),
    (["--port", "/dev/none", "--camera", "{tmp}/nothing"], ["no such camera"]),
    (["--port", "/dev/none", "--camera", "{tmp}/video0", "--seed", "3"], ["--seed", "--sim"]),
    (["--sim", "--port", "/dev/none"], ["one bot"]),
    (["--cloud", "--port", "/dev/none"], ["one bot"]),
    (["--sim", "--camera", "{tmp}/video0"], ["--camera", "simulated"]),
    (["--port", "/dev/none", "--camera", "{tmp}/video0", "--set", "sim.plant.leaves=3"],
     ["sim.plant.leaves"]),
])
def test_bad_input_is_one_line_and_exit_2(field, capsys, argv, words):
    argv = [a.replace("{tmp}", str(field)) for a in argv]
    code, _, err = run_cli(capsys, "field", "--bed", field / "bed.toml", "--out", field / "bed",
                        *argv)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("flowerpose: error: "), err
    assert all(word in lines[0] for word in words), lines[0]
    assert not (field / "bed").exists() and "Traceback" not in err


def test_the_frame_choice_follows_each_plants_scan(field):
    camera = usb_camera.UsbCamera(field / "video0", config=usb_camera.UsbCameraConfig(
        width=64, height=48, choose=usb_camera.FrameChoice(10.0)))
    try:
        camera.choose_frames(usb_camera.FrameChoice(25.0))
        assert camera.config.choose.duration_s == 25.0
        camera.start_recording(field / "scan" / "video.mp4")
        with pytest.raises(usb_camera.CameraError, match="cannot change while recording"):
            camera.choose_frames(None)
        camera.stop_recording()
        camera.choose_frames(None)
        assert camera.config.choose is None
    finally:
        camera.close()
