"""Logging: the CLI's level on stderr, and the records a running compositor publishes on its telemetry."""

import io
import logging
import sys

import pytest

from hmdrt.cli import build_parser
from hmdrt.console import logs


@pytest.fixture
def restore_logging():
    root = logging.getLogger()
    handlers, levels = list(root.handlers), {n: logging.getLogger(n).level for n in logs.PACKAGES}
    yield
    root.handlers[:] = handlers
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)


def test_the_cli_level_decides_what_reaches_stderr(capsys, restore_logging):
    logs.configure("warning")
    logging.getLogger("hmdrt.compositor.daemon").info("quiet")
    logging.getLogger("hmdrt.drivers.host").warning("driver x crashed")
    logs.configure("info")  # again: one console handler, not two
    logging.getLogger("hmdrt.replay.player").info("loud")
    err = capsys.readouterr().err.splitlines()
    assert err == ["hmdrt: WARNING: hmdrt.drivers.host: driver x crashed", "hmdrt: INFO: hmdrt.replay.player: loud"]


def test_the_console_writes_to_stderr_as_it_is_when_a_record_comes(restore_logging, monkeypatch):
    """A program (or a test) that swaps sys.stderr after configure() gets the records, once: none go to the old
    stream, and configure() leaves one console handler whatever was there."""
    logging.getLogger().addHandler(logs._Console())  # one left behind, say by a caller that saved and restored
    logs.configure("warning")
    later = io.StringIO()
    monkeypatch.setattr(sys, "stderr", later)
    logging.getLogger("hmdrt.compositor.daemon").warning("swapped")
    assert later.getvalue() == "hmdrt: WARNING: hmdrt.compositor.daemon: swapped\n"


def test_verbose_and_log_level_parse_to_a_level():
    assert build_parser().parse_args(["-v", "keys", "x"]).log_level == "info"
    assert build_parser().parse_args(["--log-level", "debug", "keys", "x"]).log_level == "debug"
    assert build_parser().parse_args(["keys", "x"]).log_level == "warning"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--log-level", "loud", "keys", "x"])


def test_a_compositors_handler_publishes_the_packages_records_while_attached(restore_logging):
    sent = []
    handler = logs.TelemetryHandler(lambda topic, fields: sent.append((topic, fields)))
    handler.attach()
    logging.getLogger("hmdrt.compositor.daemon").info("reloaded run.toml")
    logging.getLogger("elsewhere").warning("not ours")
    handler.detach()
    logging.getLogger("hmdrt.drivers.host").warning("after detach")
    assert sent == [("log", {"level": "info", "message": "reloaded run.toml", "logger": "hmdrt.compositor.daemon"})]


def test_a_record_that_cannot_be_published_does_not_raise(restore_logging, capsys):
    def closed(topic, fields):
        raise RuntimeError("socket closed")

    handler = logs.TelemetryHandler(closed)
    handler.attach()
    try:
        logging.getLogger("hmdrt.present.output").error("cannot write frame 3")  # must not raise
    finally:
        handler.detach()
    assert handler.dropped == 1 and "Traceback" not in capsys.readouterr().err
