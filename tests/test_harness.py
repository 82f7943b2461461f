"""The test harness itself (tests/conftest.py): every test runs under a time limit, and the ZeroMQ fixtures give
sockets that never block teardown."""

import signal

import pytest
import zmq


@pytest.mark.skipif(not hasattr(signal, "SIGALRM"), reason="no SIGALRM on this platform")
def test_every_test_runs_under_a_time_limit():
    remaining = signal.getitimer(signal.ITIMER_REAL)[0]
    assert 0 < remaining <= 300


def test_fixture_sockets_linger_0_on_the_tests_own_context(context, sockets):
    sock = sockets(zmq.PUB)
    assert sock.getsockopt(zmq.LINGER) == 0 and sock.context is context and context is not zmq.Context.instance()
