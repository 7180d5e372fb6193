"""One open serial port as the Farmduino client uses it: a reader thread that queues each
received line (and a `Dropped` marker when the port fails), and writes under a lock, so an
emergency stop may be written from any thread. What the lines mean, and getting the link
back after a drop (reopening with backoff, bringing the firmware up again), belong to the
client (`farmduino.py`)."""

from __future__ import annotations

import contextlib
import queue
import threading

import serial

from flowerpose.hardware.bot_errors import ConnectionLostError

#: Longest run of bytes without a line end kept: more is line noise, dropped.
MAX_LINE_BYTES = 4096


class LinkDropped(ConnectionLostError):
    """The port failed under the client, which recovers it."""

    def __init__(self, link: str, detail: str):
        self.detail = detail
        super().__init__(link, detail)


class Dropped:
    """Put in the line queue by the reader when the port fails."""

    def __init__(self, detail: str):
        self.detail = detail


class SerialLink:
    """The port `path` opened at `baud` (serial.SerialException, OSError or ValueError when
    it cannot be), read by a thread into `lines` (str, then a `Dropped` when it fails)."""

    def __init__(self, path: str, baud: int):
        self.path = path
        self._port = serial.Serial(path, baud, timeout=0.05, write_timeout=2.0)
        self._lock = threading.Lock()
        self._open = True
        self.lines: queue.Queue[str | Dropped] = queue.Queue()
        self._stop = threading.Event()
        self._reader = threading.Thread(target=self._read, name=f"farmduino-reader {path}",
                                        daemon=True)
        self._reader.start()

    def write(self, data: bytes) -> None:
        """Send `data`; LinkDropped when the port is closed or fails."""
        with self._lock:
            if not self._open:
                raise LinkDropped(self.path, "the port is not open")
            try:
                self._port.write(data)
            except (serial.SerialException, OSError) as error:
                raise LinkDropped(self.path, str(error)) from None

    def try_write(self, data: bytes) -> bool:
        """Send `data` if the port lets us (an emergency stop, an abort); whether it went."""
        try:
            self.write(data)
        except LinkDropped:
            return False
        return True

    def close(self) -> None:
        """Stop the reader (from any thread but its own it is waited for) and close."""
        self._stop.set()
        if self._reader is not threading.current_thread():
            self._reader.join(1.0)
        with self._lock:
            if self._open:
                self._open = False
                with contextlib.suppress(serial.SerialException, OSError):
                    self._port.close()

    def _read(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            try:
                chunk = self._port.read(max(1, self._port.in_waiting))
            except (serial.SerialException, OSError, TypeError) as error:
                # TypeError: pyserial's read on a port closed under it.
                if not self._stop.is_set():
                    self.lines.put(Dropped(str(error)))
                return
            if not chunk:
                continue
            *complete, buffer = (buffer + chunk).split(b"\n")
            for raw in complete:
                text = raw.decode("ascii", "replace").strip()
                if text:
                    self.lines.put(text)
            if len(buffer) > MAX_LINE_BYTES:
                buffer = b""
