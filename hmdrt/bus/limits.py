"""How much of the compositor one client may take (docs/runtime.md, Access): a token bucket per peer and a pace for
the socket as a whole, so that a flood of requests or samples costs the renderer a bounded share of a core and the
excess is counted rather than served.

A peer is who ZeroMQ says sent a message: its CURVE key (User-Id) where CURVE authenticated it, else its
Peer-Address: on ipc:// the sending process (uid:gid:pid, from the kernel), on tcp:// the IP address. TCP does not
say which local user connected, so every local client of a loopback tcp:// socket is one peer there. A message
over its peer's budget is refused and counted; once the socket's budget is spent, reading waits (`paused_s`) and
what waits stays queued in ZeroMQ, up to its high-water mark.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

import zmq

MAX_PEERS = 1024  # buckets kept, of the peers heard from last; one heard from again after that starts full


@dataclass(frozen=True)
class Budget:
    """Messages a second per peer (with a burst of that many at once) and for the socket as a whole."""

    per_peer_hz: float
    burst: float
    socket_hz: float


# control: `stats` costs the compositor about 0.5 ms, so a peer's 100 a second is at most ~5% of a core, and the
# socket's 500 reads a second bound the refusals' cost too; `hmdrt watch` asks once a second
CONTROL = Budget(per_peer_hz=100, burst=200, socket_hz=500)
# ingest: a 2 kHz binocular tracker with a 1 kHz head tracker in one process publishes about 3,000 a second
INGEST = Budget(per_peer_hz=5_000, burst=5_000, socket_hz=20_000)


def peer(frame: zmq.Frame) -> str:
    """Who sent a received message (module docstring); "" where ZeroMQ does not say (inproc)."""
    for name in ("User-Id", "Peer-Address"):
        try:
            value = frame.get(name)
        except zmq.ZMQError:  # not set for this message
            continue
        if value:
            return value
    return ""


class TokenBucket:
    """`rate` tokens a second, at most `burst` held; a message takes one."""

    __slots__ = ("rate", "burst", "tokens", "t")

    def __init__(self, rate: float, burst: float, now: float):
        self.rate, self.burst, self.tokens, self.t = rate, burst, burst, now

    def _refill(self, now: float) -> None:
        self.tokens = min(self.burst, self.tokens + (now - self.t) * self.rate)
        self.t = now

    def take(self, now: float) -> bool:
        """Take a token if there is one; whether there was."""
        self._refill(now)
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def wait_s(self, now: float) -> float:
        """Seconds until a token is there (0: one is)."""
        self._refill(now)
        return max(1.0 - self.tokens, 0.0) / self.rate


class Limiter:
    """One socket's budget: before each read wait_s() says how long the socket's budget makes reading wait, and
    admit(peer) takes the message from it and from the peer's bucket, refusing (and counting) it when the peer's is
    empty. Used by the one thread that reads the socket."""

    def __init__(self, budget: Budget, clock: Callable[[], float] = time.monotonic):
        self.budget = budget
        self._clock = clock
        self._socket = TokenBucket(budget.socket_hz, budget.socket_hz, clock())
        self._peers: OrderedDict[str, TokenBucket] = OrderedDict()
        self.refused = 0  # messages over their peer's budget
        self.paused_s = 0.0  # time reading waited because the socket's budget was spent

    def wait_s(self) -> float:
        """Seconds to wait before reading the next message, counted as paused (0: read now)."""
        wait = self._socket.wait_s(self._clock())
        self.paused_s += wait
        return wait

    def admit(self, sender: str) -> bool:
        """Whether a message read from `sender` is within its peer's budget; it counts against the socket's either
        way, and a refusal is counted."""
        now = self._clock()
        self._socket.take(now)
        bucket = self._peers.get(sender)
        if bucket is None:
            bucket = self._peers[sender] = TokenBucket(self.budget.per_peer_hz, self.budget.burst, now)
            if len(self._peers) > MAX_PEERS:
                self._peers.popitem(last=False)
        else:
            self._peers.move_to_end(sender)
        if bucket.take(now):
            return True
        self.refused += 1
        return False

    def counts(self) -> dict[str, float]:
        return {"refused": self.refused, "paused_s": round(self.paused_s, 3)}


def silent(last_heard: dict[str, int | None], now_ns: int, expiry_ns: int) -> list[str]:
    """The names in a table of devices that have been silent for over expiry_ns (None: never heard from usefully),
    whose slots a new device may take."""
    return [name for name, t in last_heard.items() if t is None or now_ns - t > expiry_ns]
