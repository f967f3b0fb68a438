"""CURVE security for ZeroMQ: every socket authenticated and encrypted, for deployments
whose sockets leave loopback (the paper's two PCs, containers on a network).

``semservo keys DIR`` makes the keys (pyzmq's ``zmq.auth``): a server keypair that every
binding socket presents, a client keypair that every connecting socket presents, and
``DIR/authorized/`` holding the client public keys that servers accept. Point every
process at the folder with ``SEMSERVO_CURVE_KEYS_DIR=DIR``; a lab PC that only runs
scripts needs ``client.key_secret``, ``client.key`` and ``server.key``.

How it applies: :func:`context` hands out a ZeroMQ context whose sockets configure
themselves as CURVE servers when they bind and as CURVE clients when they connect, so
no socket in the code base needs to know. Each process that binds runs a ZAP
authenticator (a thread) that admits only the authorized client keys.

Without keys, a service whose sockets would leave loopback refuses to start
(:func:`require_keys_off_loopback`), as the gateway refuses to serve off loopback
without its API token.
"""

from __future__ import annotations

import ipaddress
import logging
import shutil
import threading
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

log = logging.getLogger(__name__)

SERVER, CLIENT, AUTHORIZED = "server", "client", "authorized"


class SecurityError(RuntimeError):
    """Keys are missing or unreadable, or a socket would leave loopback without them."""


def make_keys(folder: Path) -> dict[str, Path]:
    """Create the server and client keypairs in ``folder`` and authorize the client.
    Existing keys are kept (making keys twice must not lock out a deployed PC)."""
    folder.mkdir(parents=True, exist_ok=True)
    made = {}
    for name in (SERVER, CLIENT):
        public, secret = folder / f"{name}.key", folder / f"{name}.key_secret"
        if not (public.is_file() and secret.is_file()):
            zmq.auth.create_certificates(folder, name)
        secret.chmod(0o600)
        made[name] = secret
    authorized = folder / AUTHORIZED
    authorized.mkdir(exist_ok=True)
    shutil.copy(folder / f"{CLIENT}.key", authorized / f"{CLIENT}.key")
    made[AUTHORIZED] = authorized
    return made


class Keys:
    """The keys one process uses, read from a folder made by :func:`make_keys`."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        try:
            self.server_public, self.server_secret = _load(self.folder / f"{SERVER}.key_secret", secret=True)
            self.client_public, self.client_secret = _load(self.folder / f"{CLIENT}.key_secret", secret=True)
        except SecurityError:
            # A scripts-only PC may hold just the client keypair and the server's public key.
            self.server_secret = None
            self.server_public, _ = _load(self.folder / f"{SERVER}.key", secret=False)
            self.client_public, self.client_secret = _load(self.folder / f"{CLIENT}.key_secret", secret=True)
        self.authorized = self.folder / AUTHORIZED


def _load(path: Path, *, secret: bool) -> tuple[bytes, bytes | None]:
    try:
        public, secret_key = zmq.auth.load_certificate(path)
    except (OSError, ValueError) as error:
        raise SecurityError(f"cannot read the CURVE key {path}: {error} (make keys with: semservo keys DIR)") from None
    if secret and secret_key is None:
        raise SecurityError(f"{path} holds no secret key")
    return public, secret_key


class CurveSocket(zmq.Socket):
    """A socket that is a CURVE server when it binds and a CURVE client when it
    connects (its context carries the keys)."""

    def bind(self, addr: str):
        keys: Keys = self.context.curve_keys
        if keys.server_secret is None:
            raise SecurityError(f"binding {addr} needs the server's secret key in {keys.folder}")
        self.context.start_authenticator()
        self.curve_secretkey = keys.server_secret
        self.curve_publickey = keys.server_public
        self.curve_server = True
        return super().bind(addr)

    def connect(self, addr: str):
        keys: Keys = self.context.curve_keys
        self.curve_secretkey = keys.client_secret
        self.curve_publickey = keys.client_public
        self.curve_serverkey = keys.server_public
        return super().connect(addr)


class CurveContext(zmq.Context):
    """A context whose sockets use CURVE (see :class:`CurveSocket`)."""

    _socket_class = CurveSocket
    # Declared here: pyzmq takes attributes a subclass does not declare for socket options.
    curve_keys: Keys | None = None
    _authenticator: ThreadAuthenticator | None = None
    _authenticator_lock: threading.Lock | None = None

    def __init__(self, keys: Keys, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.curve_keys = keys
        self._authenticator: ThreadAuthenticator | None = None
        self._authenticator_lock = threading.Lock()

    def start_authenticator(self) -> None:
        """ZAP for this context: only the authorized client keys get in (once per context)."""
        with self._authenticator_lock:
            if self._authenticator is None:
                self._authenticator = ThreadAuthenticator(self, log=logging.getLogger("semservo.zap"))
                self._authenticator.start()
                self._authenticator.configure_curve(domain="*", location=str(self.curve_keys.authorized))

    def _stop_authenticator(self) -> None:
        with self._authenticator_lock:
            if self._authenticator is not None:
                self._authenticator.stop()
                self._authenticator = None

    def term(self) -> None:
        self._stop_authenticator()
        super().term()

    def destroy(self, linger: int | None = None) -> None:
        self._stop_authenticator()
        super().destroy(linger)


def context(keys_dir: Path | None) -> zmq.Context:
    """A new context: CURVE when ``keys_dir`` is set, plain otherwise."""
    return CurveContext(Keys(keys_dir)) if keys_dir is not None else zmq.Context()


_defaults: dict[Path | None, zmq.Context] = {}
_default_lock = threading.Lock()


def default_context() -> zmq.Context:
    """The process's shared context for the keys the settings name now, secured or
    plain (what the transport classes use when given none: the launcher, the CLI, lab
    tools)."""
    from semservo.config import Settings

    keys_dir = Settings().curve_keys_dir
    with _default_lock:
        shared = _defaults.get(keys_dir)
        if shared is None or shared.closed:
            shared = _defaults[keys_dir] = (CurveContext(Keys(keys_dir)) if keys_dir is not None
                                            else zmq.Context.instance())
        return shared


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def require_keys_off_loopback(settings) -> None:
    """Refuse (:class:`SecurityError`) when any of this deployment's ZeroMQ sockets would
    bind or connect beyond loopback with no CURVE keys configured."""
    if settings.curve_keys_dir is not None:
        return
    hosts = {"bind_host": settings.bind_host}
    for section in ("fakelab", "imageserver", "estimator", "stage", "controller", "gateway"):
        hosts[f"{section}.host"] = getattr(settings, section).host
    exposed = {name: host for name, host in hosts.items() if not is_loopback(host)}
    if exposed:
        where = ", ".join(f"{name}={host}" for name, host in exposed.items())
        raise SecurityError(f"ZeroMQ sockets would leave loopback ({where}) without encryption: make keys with "
                            f"'semservo keys DIR' and set SEMSERVO_CURVE_KEYS_DIR=DIR on every PC")
