"""Who may use the bus (docs/runtime.md, Access): loopback by default, ZeroMQ CURVE with an allow-list otherwise.

A compositor whose sockets all bind loopback trusts the local clients that can reach them: this user alone on
the default ipc:// sockets (hmdrt.bus.local), every local user on a tcp:// one (open_to_local_users). One that
binds another address (`*`, 0.0.0.0, a host name, an interface) must be given a [security] section: its three
sockets are then CURVE servers (RFC 26) and a ZAP handler (RFC 27) admits only the listed client
public keys. Every handshake on those sockets is counted: admitted, or refused (no CURVE, a wrong
server key, a key not on the list); a refused client never reaches the compositor.

Keys are ZeroMQ certificate files as zmq.auth.create_certificates writes them: NAME.key holds the
public key, NAME.key_secret both keys (mode 0600).
"""

from __future__ import annotations

import ipaddress
import os
import queue
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth
from zmq.utils import z85
from zmq.utils.monitor import recv_monitor_message

from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.files.atomic import write_atomic

ZAP_ENDPOINT = "inproc://zeromq.zap.01"  # where libzmq asks a context's ZAP handler (RFC 27)
DOMAIN = b"hmdrt"  # the ZAP domain of the compositor's sockets
POLL_MS = 50
REFUSED = zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH
EVENTS = REFUSED | zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_MONITOR_STOPPED
LOCAL_TRANSPORTS = ("inproc", "ipc")  # reachable from this host only


def is_loopback(endpoint: str) -> bool:
    """Whether a bind endpoint is reachable from this host only: inproc, ipc, or tcp on 127.0.0.0/8, ::1 or
    localhost. `*`, 0.0.0.0, host names and interface names are not. Something that is no endpoint at all
    counts as loopback, so that its bind fails with its own message."""
    transport, sep, address = endpoint.partition("://")
    if not sep or transport in LOCAL_TRANSPORTS:
        return True
    host = address.rpartition(":")[0] if ":" in address else address
    host = host.strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_binds(endpoints: dict[str, str], secured: bool) -> None:
    """ConfigError for the first endpoint that is not loopback when there is no CURVE to guard it."""
    if secured:
        return
    for name, endpoint in endpoints.items():
        if not is_loopback(endpoint):
            raise ConfigError(
                f"{name} = {endpoint} is not loopback: binding it needs CURVE, a [security] section with "
                f'server_key and allowed_clients (keys from "hmdrt keys NAME"; docs/runtime.md, Access)'
            )


def open_to_local_users(endpoints: dict[str, str], secured: bool) -> list[str]:
    """The names of the bound endpoints every local user can reach: tcp:// ones (loopback, as check_binds makes sure)
    without CURVE. ipc:// ones lie in a private folder (hmdrt.bus.local)."""
    if secured:
        return []
    return [name for name, endpoint in endpoints.items() if endpoint.partition("://")[0] not in LOCAL_TRANSPORTS]


# --- key files -----------------------------------------------------------------------------------------------------


def write_keypair(directory: str | Path, name: str, force: bool = False) -> tuple[Path, Path]:
    """Write a new CURVE keypair as DIR/NAME.key (public, 0644) and DIR/NAME.key_secret (secret, 0600); an
    existing key is replaced only with force. Returns (public, secret) paths."""
    if not name or name in (".", "..") or "/" in name or os.sep in name:
        raise ConfigError(f"a key name is a plain file name without a folder, got {name!r} (use --dir)")
    directory = Path(directory)
    public, secret = directory / f"{name}.key", directory / f"{name}.key_secret"
    for path in (public, secret):
        if path.exists() and not force:
            raise ConfigError(f"{path} exists; pass --force to replace the keypair")
    with tempfile.TemporaryDirectory() as tmp:  # 0700: the secret is never readable by others on the way
        made = zmq.auth.create_certificates(tmp, name)
        texts = [Path(p).read_bytes() for p in made]
    written: list[Path] = []
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for path, text, mode in ((secret, texts[1], 0o600), (public, texts[0], 0o644)):
            write_atomic(path, text, mode=mode, replace=force)
            written.append(path)
    except (OSError, HmdrtError) as exc:
        for done in written:  # no half keypair: a secret without its public file, or an old public beside a new secret
            done.unlink(missing_ok=True)
        if isinstance(exc, FileExistsError):
            raise ConfigError(f"{path} exists; pass --force to replace the keypair") from None
        raise ConfigError(f"cannot write the keypair in {directory}: {exc}") from None
    return public, secret


def _load(path: str | Path, what: str) -> tuple[bytes, bytes | None]:
    try:
        return zmq.auth.load_certificate(path)
    except (OSError, ValueError) as exc:
        reason = "not found" if not Path(path).exists() else f"not a ZeroMQ key file ({exc})"
        raise ConfigError(f"{what} {path}: {reason}") from None


def load_public(path: str | Path, what: str = "public key") -> bytes:
    """The Z85 public key of a key file (NAME.key or NAME.key_secret)."""
    return _load(path, what)[0]


def load_secret(path: str | Path, what: str = "secret key") -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys of a secret key file (NAME.key_secret)."""
    public, secret = _load(path, what)
    if secret is None:
        raise ConfigError(f"{what} {path} holds no secret key (give the NAME.key_secret file)")
    return public, secret


@dataclass(frozen=True)
class ClientKeys:
    """What a CURVE client needs: the server's public key and its own keypair (Z85)."""

    server_public: bytes
    public: bytes
    secret: bytes

    @classmethod
    def load(cls, server_key: str | Path, client_key: str | Path) -> ClientKeys:
        """From the server's public key file and the client's secret key file."""
        public, secret = load_secret(client_key, "--client-key")
        return cls(load_public(server_key, "--server-key"), public, secret)

    @classmethod
    def from_options(cls, server_key: str | None, client_key: str | None) -> ClientKeys | None:
        """From --server-key and --client-key: both or neither (None: a plain, unauthenticated client)."""
        if not server_key and not client_key:
            return None
        if not (server_key and client_key):
            raise ConfigError("--server-key PUBLIC_KEY_FILE and --client-key SECRET_KEY_FILE go together")
        return cls.load(server_key, client_key)

    def apply(self, sock: zmq.Socket) -> None:
        """Make sock a CURVE client of the server (before it connects)."""
        sock.setsockopt(zmq.CURVE_SERVERKEY, self.server_public)
        sock.setsockopt(zmq.CURVE_PUBLICKEY, self.public)
        sock.setsockopt(zmq.CURVE_SECRETKEY, self.secret)

    def set_defaults(self, context: zmq.Context) -> None:
        """Make every socket the context creates from now on a CURVE client (for code that makes its own)."""
        for option, value in (
            (zmq.CURVE_SERVERKEY, self.server_public),
            (zmq.CURVE_PUBLICKEY, self.public),
            (zmq.CURVE_SECRETKEY, self.secret),
        ):
            context.setsockopt(option, value)


@dataclass(frozen=True)
class ServerKeys:
    """A CURVE server's keypair and the client public keys it admits (Z85)."""

    public: bytes
    secret: bytes
    allowed: frozenset[bytes]

    @classmethod
    def load(cls, server_key: str | Path, allowed_clients: list[str]) -> ServerKeys:
        public, secret = load_secret(server_key, "security.server_key:")
        allowed = frozenset(load_public(p, "security.allowed_clients:") for p in allowed_clients)
        return cls(public, secret, allowed)


# --- the server side ----------------------------------------------------------------------------------------------


class Guard:
    """Makes sockets CURVE servers of one keypair and answers their ZAP requests on a thread: a client key on
    the allow-list is admitted (its key becomes the messages' User-Id), any other refused. Counts the
    handshakes on those sockets as `admitted` and `refused`.

    libzmq asks one ZAP handler per context, so a context has at most one Guard. It must exist before the
    sockets bind: a CURVE server without a ZAP handler would admit any client that knows its public key.
    """

    def __init__(self, context: zmq.Context, keys: ServerKeys):
        self.keys = keys
        public, secret = zmq.curve_keypair()  # for the compositor's own drivers, never written anywhere
        self.own_keys = ClientKeys(keys.public, public, secret)
        self._allowed = keys.allowed | {public}
        self.admitted = 0
        self.refused = 0
        self._zap = context.socket(zmq.REP)
        self._zap.setsockopt(zmq.LINGER, 0)
        try:
            self._zap.bind(ZAP_ENDPOINT)
        except zmq.ZMQError as exc:
            self._zap.close()
            raise ConfigError(f"cannot start the CURVE handler: {exc} (one secured compositor per process)") from None
        self._monitors: queue.SimpleQueue[zmq.Socket] = queue.SimpleQueue()  # handed to the thread
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="zap", daemon=True)
        self._thread.start()

    def serve(self, sock: zmq.Socket) -> None:
        """Make sock a CURVE server guarded by this handler, its handshakes counted (before it binds)."""
        sock.setsockopt(zmq.CURVE_SERVER, 1)
        sock.setsockopt(zmq.CURVE_SECRETKEY, self.keys.secret)
        sock.setsockopt(zmq.ZAP_DOMAIN, DOMAIN)
        self._monitors.put(sock.get_monitor_socket(EVENTS))

    def counts(self) -> dict[str, int]:
        return {"admitted": self.admitted, "refused": self.refused}

    def _answer(self, request: list[bytes]) -> list[bytes]:
        """The ZAP reply (RFC 27): 200 and the key as User-Id for an allowed CURVE key, 400 otherwise."""
        if len(request) < 6:  # libzmq's own requests never are; the REP socket still owes an answer
            return [b"1.0", request[1] if len(request) > 1 else b"", b"400", b"malformed ZAP request", b"", b""]
        version, request_id, domain, mechanism = request[0], request[1], request[2], request[5]
        if version != b"1.0":
            return [version, request_id, b"400", b"unsupported ZAP version", b"", b""]
        if domain != DOMAIN and mechanism == b"NULL":
            return [version, request_id, b"200", b"OK", b"", b""]  # another socket of the context: not ours
        if mechanism == b"CURVE" and len(request) > 6:
            key = z85.encode(request[6])
            if key in self._allowed:
                return [version, request_id, b"200", b"OK", key, b""]
            return [version, request_id, b"400", b"client key not allowed", b"", b""]
        return [version, request_id, b"400", b"CURVE required", b"", b""]

    def _run(self) -> None:
        poller = zmq.Poller()
        poller.register(self._zap, zmq.POLLIN)
        monitors: list[zmq.Socket] = []
        try:
            while not self._stop.is_set():
                while not self._monitors.empty():
                    monitors.append(self._monitors.get())
                    poller.register(monitors[-1], zmq.POLLIN)
                for sock, _ in poller.poll(POLL_MS):
                    if sock is self._zap:
                        self._zap.send_multipart(self._answer(self._zap.recv_multipart()))
                        continue
                    event = recv_monitor_message(sock)["event"]
                    if event == zmq.EVENT_HANDSHAKE_SUCCEEDED:
                        self.admitted += 1
                    elif event & REFUSED:
                        self.refused += 1
                    elif event == zmq.EVENT_MONITOR_STOPPED:  # its socket has closed
                        poller.unregister(sock)
                        monitors.remove(sock)
                        sock.close()
        finally:
            for sock in monitors:
                sock.close()
            while not self._monitors.empty():
                self._monitors.get().close()
            self._zap.close()

    def close(self) -> None:
        """Stop answering; sockets it serves should be closed first (new clients could not be answered)."""
        self._stop.set()
        self._thread.join()
