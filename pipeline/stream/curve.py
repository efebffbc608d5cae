"""ZeroMQ CURVE for a graph that spans hosts: encryption and authentication of every
socket, with keys in the daemon's state directory.

``STATE/curve/`` (mode 0700) holds ``server.key`` / ``server.key_secret`` (every bound
socket serves with them) and ``client.key`` / ``client.key_secret`` (every connecting socket
presents them); ``authorized/`` holds the public client keys a bound socket accepts (the
ZAP authenticator of each process reads it). Secret files are mode 0600. A stage turns
CURVE on when ``$TCSPC_CURVE_DIR`` names that directory (the daemon sets it; for stages
started by hand on another host, copy the directory there). The daemon turns it on when any
endpoint is tcp:// (loopback too: any local account reaches it), or by config; ipc://
endpoints are private to the state directory's owner.
"""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

import zmq

CURVE_ENV = "TCSPC_CURVE_DIR"
_auth_lock = threading.Lock()
_authenticators: dict[int, object] = {}  # per context: one ZAP handler thread


def ensure_keys(state: str | Path) -> Path:
    """Create (once) and return the key directory ``STATE/curve``."""
    import zmq.auth

    d = Path(state) / "curve"
    auth = d / "authorized"
    if not (d / "server.key_secret").exists() or not (d / "client.key_secret").exists():
        d.mkdir(parents=True, exist_ok=True)
        os.chmod(d, 0o700)
        zmq.auth.create_certificates(str(d), "server")
        zmq.auth.create_certificates(str(d), "client")
    auth.mkdir(exist_ok=True)
    shutil.copyfile(d / "client.key", auth / "client.key")
    for p in d.glob("*.key_secret"):
        os.chmod(p, 0o600)
    os.chmod(d, 0o700)
    return d


def key_dir() -> Path | None:
    """The key directory when CURVE is on for this process, else None."""
    v = os.environ.get(CURVE_ENV)
    return Path(v) if v else None


def needs_curve(endpoints: list[str]) -> bool:
    """True when any endpoint is tcp://, loopback included: every local account can
    connect to a loopback port, and ZeroMQ assembles a message's frames (each at most
    ZMQ_MAXMSGSIZE, however many) before a stage sees it, so only an authenticated peer may
    deliver one. (ipc:// sockets live in the daemon's 0700 state directory.)"""
    return any(ep.startswith("tcp://") for ep in endpoints)


def release(ctx: zmq.Context) -> None:
    """Stop the ZAP authenticator :func:`serve` started on ``ctx`` (before ``ctx.term()``,
    which waits for every socket of the context, the authenticator's too)."""
    with _auth_lock:
        auth = _authenticators.pop(id(ctx), None)
    if auth is not None:
        auth.stop()


def serve(sock: zmq.Socket, keys: Path | None = None) -> None:
    """Make ``sock`` (about to bind) a CURVE server accepting only authorized clients."""
    import zmq.auth
    from zmq.auth.thread import ThreadAuthenticator

    keys = keys or key_dir()
    if keys is None:
        return
    with _auth_lock:
        ctx = sock.context
        if id(ctx) not in _authenticators:
            auth = ThreadAuthenticator(ctx)
            auth.start()
            auth.configure_curve(domain="*", location=str(keys / "authorized"))
            _authenticators[id(ctx)] = auth
    public, secret = zmq.auth.load_certificate(str(keys / "server.key_secret"))
    sock.curve_secretkey, sock.curve_publickey = secret, public
    sock.curve_server = True


def client(sock: zmq.Socket, keys: Path | None = None) -> None:
    """Make ``sock`` (about to connect) a CURVE client of the graph's server key."""
    import zmq.auth

    keys = keys or key_dir()
    if keys is None:
        return
    public, secret = zmq.auth.load_certificate(str(keys / "client.key_secret"))
    server, _ = zmq.auth.load_certificate(str(keys / "server.key"))
    sock.curve_secretkey, sock.curve_publickey = secret, public
    sock.curve_serverkey = server


def stop_authenticators() -> None:
    with _auth_lock:
        for auth in _authenticators.values():
            auth.stop()
        _authenticators.clear()
