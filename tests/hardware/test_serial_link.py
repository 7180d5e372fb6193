"""The serial link alone, on a pseudo-terminal: lines in, bytes out, a drop, a close."""

import os
import tty

import pytest

from flowerpose.hardware.backends.serial_link import Dropped, LinkDropped, SerialLink


@pytest.fixture
def pty():
    controller, device = os.openpty()
    tty.setraw(device)
    yield controller, os.ttyname(device)
    for fd in (controller, device):
        try:
            os.close(fd)
        except OSError:
            pass


def test_lines_arrive_whole_and_writes_go_out(pty, watchdog):
    controller, path = pty
    link = SerialLink(path, 115200)
    try:
        os.write(controller, b"R01 Q1\r\nR02")
        os.write(controller, b" Q1\r\n\r\nnoise")
        assert [link.lines.get(timeout=5), link.lines.get(timeout=5)] == ["R01 Q1", "R02 Q1"]
        link.write(b"F82 Q2\r\n")
        assert os.read(controller, 64) == b"F82 Q2\r\n"
    finally:
        link.close()
    assert link.lines.empty()  # the unfinished "noise" never became a line


def test_a_closed_link_refuses_writes_and_an_emergency_stop_says_it_did_not_go(pty, watchdog):
    _, path = pty
    link = SerialLink(path, 115200)
    link.close()
    with pytest.raises(LinkDropped, match="the port is not open"):
        link.write(b"F82\r\n")
    assert link.try_write(b"E") is False
    link.close()  # twice is harmless


def test_a_port_that_fails_under_the_reader_queues_a_drop(pty, watchdog):
    controller, path = pty
    link = SerialLink(path, 115200)
    try:
        os.close(controller)  # the other end goes: reads fail with EIO
        item = link.lines.get(timeout=5)
        assert isinstance(item, Dropped) and item.detail
    finally:
        link.close()
