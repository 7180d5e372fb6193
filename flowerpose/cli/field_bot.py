"""The physical bot and its camera as the bot's commands open them (`scan`, `pollinate`,
`field` with --port or --cloud): their flags, the connection, homing and the head's USB
camera."""

from __future__ import annotations

import argparse
from pathlib import Path

from flowerpose.cli.flags import PHRASES_ATTRIBUTE
from flowerpose.errors import InputError
from flowerpose.log import LOG

#: How --cloud logs in to FarmBot's web app (scan, pollinate, field).
WEB_APP_LOGIN = ("log in with FARMBOT_TOKEN, or FARMBOT_EMAIL and FARMBOT_PASSWORD "
                 "(FARMBOT_SERVER for another server), or --token-file")


def add_token_file(p: argparse.ArgumentParser) -> None:
    p.add_argument("--token-file", type=Path, metavar="FILE", help="--cloud: a file outside "
                   "the repository, readable by its owner alone, holding a FarmBot token (its "
                   "JSON or its JWT)")


def add_field_bot_options(p: argparse.ArgumentParser, cloud: str = "") -> None:
    """--port / --cloud and their options: the physical bot (scan, pollinate, field);
    `cloud`: what else --cloud means to the command."""
    p.add_argument("--port", metavar="PORT", help="the physical bot through its Farmduino on "
                   "this serial port (e.g. /dev/ttyACM0; best /dev/serial/by-id/...)")
    p.add_argument("--cloud", action="store_true", help="the physical bot through FarmBot's web "
                   f"app{cloud}; {WEB_APP_LOGIN}")
    p.add_argument("--firmware-params", type=Path, metavar="FILE", help="--port: the bot's "
                   "firmware settings as the FarmBot web app exports them (JSON); written to "
                   "the Farmduino at connect and read back, as FarmBot OS does (default: the "
                   "settings the board holds)")
    p.add_argument("--home-here", action="store_true", help="--port: the gantry stands at "
                   "home (put there by hand): take it as home instead of homing, for a bot "
                   "without endstops or encoders")
    add_token_file(p)
    # The serial backend's errors advise its `settings`, which --firmware-params loads.
    p.set_defaults(**{PHRASES_ATTRIBUTE: {"settings": "--firmware-params"}})


def add_camera_options(p: argparse.ArgumentParser, size: str) -> None:
    """--camera, --calibration and --keep-all: the head's USB camera (scan, field); `size`:
    how the command sets the frame size."""
    p.add_argument("--camera", metavar="DEVICE", help="--port/--cloud: the head's USB camera, "
                   "best its stable path /dev/v4l/by-id/...-video-index0; records MJPG at "
                   f"{size}, 30 fps, exposure and focus locked")
    p.add_argument("--calibration", type=Path, metavar="CAMERA.json", help="--port/--cloud: "
                   "the camera's calibrated intrinsics at that size (default: estimated from "
                   "a 62.2 degree horizontal field of view)")
    p.add_argument("--keep-all", action="store_true", help="--port/--cloud: save every frame "
                   "(30 fps: several GB for a 20-minute scan) instead of the 3 sharpest of "
                   "each of 200 bins of the path, chosen while recording")
    p.set_defaults(**{PHRASES_ATTRIBUTE: {**(p.get_default(PHRASES_ATTRIBUTE) or {}),
                                          "choose": "leaving out --keep-all"}})


def check_camera_flags(args: argparse.Namespace, needed_for: str) -> None:
    """Refuse, before the bot moves, a missing or absent --camera and a bad --calibration;
    `needed_for`: what the camera is needed for, in the message."""
    if args.camera is None:
        raise InputError("--camera", f"needed {needed_for}: the head's USB camera, e.g. "
                         "/dev/v4l/by-id/usb-...-video-index0")
    if not Path(args.camera).exists():
        raise InputError(args.camera, "no such camera device; list them with "
                         "ls -l /dev/v4l/by-id/")
    if args.calibration is not None:
        from flowerpose.scanio import read_intrinsics

        read_intrinsics(args.calibration)


def look_camera(args: argparse.Namespace):
    """The head's USB camera the close look takes its frames with (--camera, checked
    before anything moves): its factory, which takes the bot's clock."""
    check_camera_flags(args, "to fly with the close look (--set pollinate.look.views=0 "
                       "flies on the scan's poses alone)")
    from flowerpose.hardware.backends.usb_camera import UsbCamera, UsbCameraConfig

    config = UsbCameraConfig(calibration=args.calibration, focus=args.focus)
    return lambda clock: UsbCamera(args.camera, clock, config)


def field_camera(args: argparse.Namespace, width: int, height: int, duration_s: float):
    """The USB camera of --camera, checked before the bot moves: its settings
    (`UsbCameraConfig`; frames chosen over `duration_s` of bot time unless --keep-all), the
    recorder the bot films with, and what scan.json records of it."""
    check_camera_flags(args, "to scan")
    from flowerpose.hardware.backends.usb_camera import FrameChoice, UsbCamera, UsbCameraConfig
    from flowerpose.hardware.trajectory import TrajectoryRecorder

    choose = None if args.keep_all else FrameChoice(duration_s)
    camera = UsbCameraConfig(width=width, height=height, calibration=args.calibration,
                             choose=choose)
    recorder = TrajectoryRecorder(lambda clock: UsbCamera(args.camera, clock, camera))
    described = {"device": args.camera, "width": width, "height": height,
                 "intrinsics": str(args.calibration or "estimated from the field of view"),
                 "frames": "every frame" if choose is None else
                 f"the {choose.keep} sharpest of each of {choose.bins} bins of the path"}
    return camera, recorder, described


def check_field_bot_flags(args: argparse.Namespace) -> None:
    """Refuse --port's and --cloud's options given to the other bot."""
    if args.token_file is not None and not args.cloud:
        raise InputError("--token-file", "is for --cloud")
    for flag, value in (("--firmware-params", args.firmware_params),
                        ("--home-here", args.home_here)):
        if value and args.port is None:
            raise InputError(flag, "is for --port (with --cloud, FarmBot OS holds the "
                             "bot's settings and finds home)")


def field_bot(args: argparse.Namespace, camera=None, observer=None):
    """The physical bot of --port or --cloud: a function that connects to it, and what
    scan.json / flight.json record of it (no secret)."""
    check_field_bot_flags(args)
    if args.cloud:
        from flowerpose.hardware.backends.cloud_bot import FarmbotCloudBot
        from flowerpose.hardware.backends.cloud_credentials import CloudCredentials

        credentials = CloudCredentials.from_environment(token_file=args.token_file)
        source = {"backend": "farmbot-cloud", "server": credentials.server}

        def connect():
            return FarmbotCloudBot(credentials, camera=camera, observer=observer)
    else:
        from flowerpose.hardware.backends.farmduino import FarmduinoBot
        from flowerpose.hardware.protocol import read_settings

        settings = None
        if args.firmware_params is not None:
            settings = read_settings(args.firmware_params)
        else:
            LOG.warning("warning: no --firmware-params: the Farmduino runs on the settings it "
                        "holds, its firmware's defaults unless they were stored in its EEPROM "
                        "(FarmBot OS, which writes them, is not connected)")
        source = {"backend": "serial", "port": args.port,
                  "firmware_params": str(args.firmware_params or "the board's own")}

        def connect():
            return FarmduinoBot(args.port, camera=camera, observer=observer,
                                settings=settings)
    return connect, source


def home_field_bot(args: argparse.Namespace, bot) -> None:
    """--port: home the bot just connected (or take where it stands, --home-here)."""
    if args.port is not None and args.home_here:
        LOG.warning(f"warning: --home-here: {bot.info.name} takes where the gantry "
                    "stands for home; every move is off by as much as it is not at home")
        bot.home_here()
    elif args.port is not None:
        # Opening the port reset the board, which lost the position: home, Z first.
        LOG.info(f"homing {bot.info.name} (Z, Y, X)")
        bot.home()
