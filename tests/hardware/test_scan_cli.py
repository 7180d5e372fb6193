"""flowerpose scan with the physical bot (--port, --cloud): the dry run, bad input as one line
and exit 2, and a whole cloud scan on fakes that is interrupted and resumed."""

import dataclasses
import functools
import json
from pathlib import Path

import numpy as np
import pytest
from cli_run import run_cli
from cloud_fakes import FakeCapture, FakeDevice, fake_factory, make_token

from flowerpose.hardware.backends import cloud_bot, usb_camera
from flowerpose.hardware.flights import scan_plan
from flowerpose.jsonio import read_json
from flowerpose.scanio import frame_files, read_trajectory

FARMBOT_VARIABLES = ("FARMBOT_TOKEN", "FARMBOT_EMAIL", "FARMBOT_PASSWORD", "FARMBOT_SERVER")


@pytest.fixture(autouse=True)
def no_credentials(monkeypatch):
    for name in FARMBOT_VARIABLES:
        monkeypatch.delenv(name, raising=False)



@pytest.mark.parametrize("bot", [["--cloud"], ["--port", "/dev/no-such-port"]])
def test_the_dry_run_prints_the_checked_moves_without_connecting(tmp_path, capsys, bot):
    code, out, err = run_cli(capsys, "scan", *bot, "--plant-at", "1.5,0.75", "--out",
                          tmp_path / "scan", "--dry-run")
    lines = out.splitlines()
    assert code == 0 and err == ""
    assert lines[0].startswith("plan: 162 waypoints around the plant at (1.500, 0.750) m")
    assert lines[1].split() == ["waypoint", "kind", "X", "mm", "Y", "mm", "Z", "mm", "yaw",
                                "cmd", "pitch", "cmd"]
    assert len(lines) == 2 + 162
    x, y, z, yaw, pitch = (float(v) for v in lines[2].split()[2:])
    assert 0 <= x <= 2722.2 and 0 <= y <= 1230 and -431.64 <= z <= 0
    assert 0 <= yaw <= 180 and 0 <= pitch <= 180
    assert not (tmp_path / "scan").exists()  # nothing connected, nothing written


@pytest.mark.parametrize("argv, words", [
    (["--cloud", "--plant-at", "1.5;0.75"], ["--plant-at", "expected X,Y in metres"]),
    (["--cloud", "--plant-at", "1.5,nan"], ["--plant-at", "finite"]),
    (["--cloud", "--plant-at", "3.2,0.75"], ["--plant-at", "outside the bed"]),
    (["--cloud", "--plant-at", "0.2,0.75", "--dry-run"], ["scan waypoint", "unreachable"]),
    (["--cloud", "--plant-at", "1.5,0.75", "--plant-radius", "0.4", "--dry-run"],
     ["camera head passes"]),
    (["--cloud", "--plant-at", "1.5,0.75", "--plant-height", "-1"], ["--plant-height"]),
    (["--cloud"], ["--plant-at", "needed"]),
    (["--plant-at", "1.5,0.75"], ["choose one bot"]),
    (["--sim", "--cloud", "--plant-at", "1.5,0.75"], ["not --sim and --cloud"]),
    (["--port", "/dev/ttyACM0", "--token-file", "{tmp}/t", "--plant-at", "1.5,0.75"],
     ["--token-file", "is for --cloud"]),
    (["--cloud", "--firmware-params", "{tmp}/p.json", "--plant-at", "1.5,0.75"],
     ["--firmware-params", "is for --port"]),
    (["--cloud", "--home-here", "--plant-at", "1.5,0.75"], ["--home-here", "is for --port"]),
    (["--port", "/dev/ttyACM0", "--plant-at", "1.5,0.75", "--camera", "{device}",
      "--firmware-params", "{tmp}/bad.json"], ["bad.json", "unknown firmware parameter 'speed'"]),
    (["--cloud", "--plant-at", "1.5,0.75"], ["--camera", "needed"]),
    (["--cloud", "--plant-at", "1.5,0.75", "--camera", "/dev/v4l/by-id/none"],
     ["/dev/v4l/by-id/none", "no such camera device"]),
    (["--cloud", "--plant-at", "1.5,0.75", "--camera", "{device}"],
     ["FARMBOT_TOKEN", "not set"]),
    (["--cloud", "--plant-at", "1.5,0.75", "--camera", "{device}", "--token-file",
      "{repo}/token.json"], ["token.json", "outside the git work tree"]),
    (["--cloud", "--plant-at", "1.5,0.75", "--camera", "{device}", "--calibration",
      "{tmp}/none.json"], ["none.json", "not found"]),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, words):
    (tmp_path / "repo" / ".git").mkdir(parents=True)
    (tmp_path / "repo" / "token.json").write_text(json.dumps(make_token()))
    (tmp_path / "video0").write_text("")
    (tmp_path / "bad.json").write_text(json.dumps({"encoder_enabled_x": 1, "speed": 3}))
    names = {"tmp": tmp_path, "repo": tmp_path / "repo", "device": tmp_path / "video0"}
    code, _, err = run_cli(capsys, "scan", *[a.format(**names) for a in argv], "--out",
                        tmp_path / "scan")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("flowerpose: error: "), err
    assert all(word in lines[0] for word in words), lines[0]
    assert "Traceback" not in err and not (tmp_path / "scan").exists()


def _small_field_scan(monkeypatch, tmp_path: Path, fps: float):
    """A fake camera at tmp_path/video0 delivering `fps` and a short scan path; returns
    the scan folder to record into and the path's config."""
    monkeypatch.setattr(usb_camera, "open_v4l2", lambda path: FakeCapture(fps=fps))
    monkeypatch.setattr(usb_camera, "UsbCameraConfig", functools.partial(
        usb_camera.UsbCameraConfig, settle_s=0.0))
    small = scan_plan.ScanConfig(scan_plan.ScanPathConfig(
        azimuth_step_deg=120.0, cylinder_bottom_m=0.2, cylinder_step_m=0.1,
        dome_polar_deg=(50.0,)), pause_s=0.05)
    monkeypatch.setattr(scan_plan, "ScanConfig", lambda: small)
    (tmp_path / "video0").write_text("")
    return tmp_path / "scan", small


@pytest.mark.slow
def test_a_cloud_scan_interrupted_and_resumed_keeps_every_frame(tmp_path, capsys, monkeypatch):
    device = FakeDevice(position_mm=(500.0, 300.0, -200.0))
    monkeypatch.setenv("FARMBOT_TOKEN", json.dumps(make_token()))
    scan, small = _small_field_scan(monkeypatch, tmp_path, fps=300.0)
    argv = ["scan", "--cloud", "--camera", tmp_path / "video0", "--width", 64, "--height", 48,
            "--plant-at", "1.5,0.75", "--plant-height", 0.22, "--out", scan]

    moves = []

    def interrupt_on_sixth_move(client):
        def move(**kwargs):
            moves.append(kwargs)
            if len(moves) == 6:
                raise KeyboardInterrupt
            return type(client).move(client, **kwargs)
        return move

    def factory():
        client = fake_factory(device)()
        client.move = interrupt_on_sixth_move(client)
        return client

    monkeypatch.setattr(cloud_bot, "farmbot_client", factory)
    code, _, err = run_cli(capsys, *argv)
    assert code == 130 and "interrupted" in err
    first = read_json(scan / "scan.json")
    # Two approach moves (up, then over waypoint 0), then waypoints 0-2; the 6th move stops.
    assert first["status"] == "interrupted" and first["completed"] == 3
    assert moves[0]["z"] == 0.0 and moves[1]["z"] == 0.0
    recorded = frame_files(scan)
    assert len(read_trajectory(scan / "trajectory.csv")) > 0 and len(recorded) > 0

    monkeypatch.setattr(cloud_bot, "farmbot_client", lambda: fake_factory(device)())
    code, out, err = run_cli(capsys, *argv)
    assert code == 0, err
    manifest = read_json(scan / "scan.json")
    assert manifest["status"] == "complete" and len(manifest["sessions"]) == 2
    assert "scan complete: 6/6 waypoints" in out
    frames = frame_files(scan)
    assert frames[:len(recorded)] == recorded and len(frames) > len(recorded)
    trajectory = read_trajectory(scan / "trajectory.csv")
    assert np.all(np.diff(trajectory.t) > 0) and trajectory.frame[-1] == len(frames) - 1
    source = manifest["source"]
    assert source["backend"] == "farmbot-cloud" and source["plant"]["at"] == [1.5, 0.75]
    assert dataclasses.asdict(small)["pause_s"] == manifest["plan"]["config"]["pause_s"]
    assert make_token()["token"]["encoded"] not in (scan / "scan.json").read_text()


@pytest.mark.slow
def test_a_serial_scan_homes_first_and_records_on_a_virtual_farmduino(tmp_path, capsys,
                                                                       monkeypatch):
    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    scan, _ = _small_field_scan(monkeypatch, tmp_path, fps=100.0)
    with virtual.VirtualFarmduino(time_scale=100.0,
                                  params=virtual.FEEDBACK_PARAMETERS) as device:
        code, out, err = run_cli(capsys, "scan", "--port", device.path, "--camera",
                              tmp_path / "video0", "--width", 64, "--height", 48, "--plant-at",
                              "1.5,0.75", "--plant-height", 0.22, "--out", scan)
    assert code == 0, err
    assert "homing" in err and "scan complete: 6/6 waypoints" in out
    assert read_json(scan / "scan.json")["source"]["backend"] == "serial"
    trajectory = read_trajectory(scan / "trajectory.csv")
    assert len(trajectory) > 0 and trajectory.frame[-1] == len(frame_files(scan)) - 1


@pytest.mark.slow
def test_a_board_on_its_defaults_scans_with_the_bots_settings_or_homed_by_hand(tmp_path, capsys,
                                                                               monkeypatch):
    """No endstops or encoders (the firmware's defaults): homing is refused in one line
    before anything moves; the web app's settings, or --home-here, make the scan work."""
    virtual = pytest.importorskip("flowerpose.hardware.backends.virtual_farmduino")
    scan, _ = _small_field_scan(monkeypatch, tmp_path, fps=100.0)
    exported = {"id": 7, "created_at": "2026-11-30T10:00:00Z", "encoder_enabled_x": 1,
                "encoder_enabled_y": 1, "encoder_enabled_z": 1, "movement_max_spd_x": 400,
                "param_config_ok": 1, "movement_home_spd_x": None}
    (tmp_path / "firmware.json").write_text(json.dumps({"firmware_config": exported}))
    argv = ["--camera", tmp_path / "video0", "--width", 64, "--height", 48, "--plant-at",
            "1.5,0.75", "--plant-height", 0.22]
    with virtual.VirtualFarmduino(time_scale=100.0) as device:
        code, out, err = run_cli(capsys, "scan", "--port", device.path, *argv, "--out", scan)
        assert code == 2 and "warning: no --firmware-params" in err
        refused = err.splitlines()[-1]
        assert "parameter 27 (movement_enable_endpoints_z)" in refused
        assert "(--firmware-params, as the FarmBot web app" in refused
        assert "(--home-here)" in refused
        assert not any(line.startswith(("F11", "F12", "F13", "G00")) for line in device.received)
        code, out, err = run_cli(capsys, "scan", "--port", device.path, *argv, "--firmware-params",
                              tmp_path / "firmware.json", "--out", tmp_path / "with-settings")
        assert code == 0, err
        assert "scan complete: 6/6 waypoints" in out and device.parameter(101) == 1.0
    with virtual.VirtualFarmduino(time_scale=100.0) as device:
        code, out, err = run_cli(capsys, "scan", "--port", device.path, *argv, "--home-here",
                              "--out", tmp_path / "by-hand")
        assert code == 0, err
        assert "--home-here" in err and "scan complete: 6/6 waypoints" in out
        assert any(line.startswith("F84") for line in device.received)


def test_the_simulated_scan_flies_the_path_its_settings_give(plant0, tmp_path, capsys):
    """scan --sim and eval's scan source plan with the same sim.viewpoints: the path the bot
    flies is the one whose cameras decide the oracle's visibility."""
    _, plant_dir = plant0
    base = ["scan", "--sim", "--plant", plant_dir, "--out", tmp_path / "scan", "--dry-run"]
    code, out, _ = run_cli(capsys, *base)
    default = sum(line.strip()[:1].isdigit() for line in out.splitlines())
    code_wide, out, _ = run_cli(capsys, *base, "--set", "sim.viewpoints.azimuth_step_deg=60")
    wide = sum(line.strip()[:1].isdigit() for line in out.splitlines())
    assert code == code_wide == 0 and 0 < wide < default
    for key, words in (("cluster.eps=0.1", "scan --sim reads sim.viewpoints.*"),
                       ("scan.camera.width=8", "--width: width and height must be at least 16")):
        code, _, err = run_cli(capsys, *base, "--set", key)
        assert code == 2 and words in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "scan").exists()
