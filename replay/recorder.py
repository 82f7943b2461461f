"""Recording the bus into a native trace: `hmdrt record --out TRACE`.

A SUB socket binds the endpoint as the compositor's ingest does (or connects to a publisher with
bind=False) and takes gaze.*, pose.* and status.* messages. Samples are written to a native trace
(replay/trace.py) as they arrive and flushed after every batch, so a killed recorder leaves a
readable file; the file is plain JSON Lines for that reason (a cut gzip stream would not read). A
trace holds one device: the first whose gaze or pose arrives, unless `device` names one; samples of
other devices are counted as ignored. Status messages are counted, malformed messages too.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import zmq
from zmq.utils.monitor import recv_monitor_message

from hmdrt.bus.messages import MAX_PAYLOAD_BYTES, MalformedMessage, Status, decode
from hmdrt.errors import ConfigError
from hmdrt.files.atomic import open_replacing
from hmdrt.replay.trace import TraceWriter

POLL_MS = 50


@dataclass
class RecorderCounts:
    """What the recorder did with the messages it heard."""

    gaze: int = 0
    pose: int = 0
    status: int = 0
    malformed: int = 0
    ignored: int = 0  # samples of a device other than the recorded one
    publishers: int = 0  # connections that completed the ZeroMQ handshake


class Recorder:
    """Records one device's samples from the bus into a native trace file."""

    def __init__(
        self,
        endpoint: str,
        out_path: str | Path,
        bind: bool = True,
        device: str | None = None,
        context: zmq.Context | None = None,
    ):
        self.out_path = Path(out_path)
        if self.out_path.suffix == ".gz":
            raise ConfigError(f"the recorder writes plain .jsonl so a cut recording stays readable, not {out_path}")
        self.device = device
        self.counts = RecorderCounts()
        self.connected = threading.Event()  # set once a publisher has connected
        self._context = context or zmq.Context.instance()
        self._socket = self._context.socket(zmq.SUB)
        self._socket.setsockopt(zmq.LINGER, 0)
        self._socket.setsockopt(zmq.RCVHWM, 100_000)
        self._socket.setsockopt(zmq.MAXMSGSIZE, 16 * MAX_PAYLOAD_BYTES)  # a peer sending more is cut off
        for prefix in (b"gaze.", b"pose.", b"status."):
            self._socket.setsockopt(zmq.SUBSCRIBE, prefix)
        self._monitor = self._socket.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
        try:
            if bind:
                self._socket.bind(endpoint)
            else:
                self._socket.connect(endpoint)
        except zmq.ZMQError as exc:
            self.close()
            raise ConfigError(f"recorder cannot {'bind' if bind else 'connect'} {endpoint}: {exc}") from None
        self.endpoint = self._socket.getsockopt(zmq.LAST_ENDPOINT).decode() if bind else endpoint

    def _write(self, out: TraceWriter, frames: list[bytes]) -> None:
        try:
            kind, device, message = decode(frames)
        except MalformedMessage:
            self.counts.malformed += 1
            return
        if isinstance(message, Status):
            self.counts.status += 1
            return
        if self.device is None:
            self.device = device
            out.header(device)
        if device != self.device:
            self.counts.ignored += 1
            return
        self.counts.gaze += kind == "gaze"
        self.counts.pose += kind == "pose"
        out.sample(message)

    def _drain(self, stream: IO[bytes], out: TraceWriter) -> None:
        """Write every message waiting on the socket, then flush the file."""
        while True:
            try:
                frames = self._socket.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            self._write(out, frames)
        stream.flush()

    def _watch_connections(self) -> None:
        while self._monitor.poll(0):
            if recv_monitor_message(self._monitor)["event"] == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                self.counts.publishers += 1
                self.connected.set()

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> RecorderCounts:
        """Record until `stop` is set or duration_s passes; returns the counts. Closes the socket."""
        stop = stop or threading.Event()
        end = None if duration_s is None else time.monotonic() + duration_s
        poller = zmq.Poller()
        poller.register(self._socket, zmq.POLLIN)
        poller.register(self._monitor, zmq.POLLIN)
        try:
            with open_replacing(self.out_path, buffering=-1) as stream:  # a link there is replaced, not followed
                out = TraceWriter(stream)
                if self.device is not None:
                    out.header(self.device)
                while not stop.is_set() and (end is None or time.monotonic() < end):
                    poller.poll(POLL_MS)
                    self._watch_connections()
                    self._drain(stream, out)
                self._drain(stream, out)
                if not out.started:  # nothing arrived: still leave a valid, empty trace
                    out.header("")
        except OSError as exc:
            raise ConfigError(f"cannot write recording {self.out_path}: {exc.strerror}") from None
        finally:
            self.close()
        return self.counts

    def summary(self) -> str:
        """The counts in a line, as `hmdrt record` prints them when it stops."""
        c = self.counts
        return (
            f"{c.gaze} gaze, {c.pose} pose ({self.device or 'no device'}); {c.malformed} malformed, "
            f"{c.ignored} of other devices ignored"
        )

    def close(self) -> None:
        """Release the sockets; safe to call twice."""
        if not self._socket.closed:
            self._socket.disable_monitor()
        self._monitor.close(0)
        self._socket.close(0)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
