"""The network surface: which endpoints are local, who can reach each one, and the
ZeroMQ CURVE keys that guard the control socket and the pose stream off loopback.

Key files are ZeroMQ certificates (the ZPL text ``zmq.auth`` reads): ``NAME.key``
holds the public key, ``NAME.key_secret`` the public and the secret key; both are
written with mode 0600 and a secret key file readable by anyone else is refused (as
ssh refuses an open private key). ``retargetd keys NAME`` writes a pair.

HMAC key files (``[input.osc] key_file``, ``retargetd replay/record --key-file``;
PROTOCOLS.md §13): UTF-8 text, lines starting with ``#`` ignored, one line of
64-128 hex digits: the key is the 32-64 bytes they spell (not the text). Mode 0600
like a secret key: a file readable by group or others is refused. ``retargetd keys
--hmac NAME`` writes ``NAME.hmac`` with 32 random bytes.
"""

from __future__ import annotations

import ipaddress
import os
import secrets
import stat
from pathlib import Path
from typing import Any

import zmq
from zmq.auth.certs import load_certificate

from retargetd.protocols.osc_auth import (
    KEY_MAX_BYTES,
    KEY_MIN_BYTES,
    DatagramVerifier,
    check_key,
)

#: Transports the daemon's ZeroMQ endpoints may use.
ZMQ_TRANSPORTS = ("tcp://", "ipc://", "inproc://")

#: Show-control tokens: URL-safe characters only (no OSC pattern characters), at
#: least 16 of them: 16 symbols of a 64-symbol alphabet are 96 bits, beyond blind
#: guessing over a network (NIST SP 800-63B asks >= 64 bits for random secrets).
TOKEN_MIN_CHARS = 16
TOKEN_MAX_CHARS = 128
_TOKEN_CHARS = frozenset(
    "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_"
)


class KeyFileError(ValueError):
    """A key file that cannot be used (one line naming the file)."""


def is_loopback_host(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``; False for anything else
    (wildcards, interface names, other addresses)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def parse_endpoint(endpoint: str) -> tuple[str, str, int | None]:
    """Split a ZeroMQ endpoint into (transport, host or path, port).

    ``tcp://HOST:PORT`` (PORT 0-65535 or ``*`` = any free port: None),
    ``ipc://PATH`` and ``inproc://NAME`` (port None).

    Raises:
        ValueError: the message says what is wrong.
    """
    if not endpoint.startswith(ZMQ_TRANSPORTS):
        raise ValueError(f"expected tcp://HOST:PORT or ipc://PATH; got {endpoint!r}")
    transport, _, rest = endpoint.partition("://")
    if transport != "tcp":
        if not rest:
            raise ValueError(f"expected a path after {transport}://; got {endpoint!r}")
        return transport, rest, None
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host:
        raise ValueError(f"expected tcp://HOST:PORT; got {endpoint!r}")
    if port_text == "*":
        return transport, host, None
    if not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise ValueError(
            f"expected a port 0-65535 (or * for any free port); got {endpoint!r}"
        )
    return transport, host, int(port_text)


def endpoint_is_local(endpoint: str) -> bool:
    """True when only this machine can reach the endpoint: ipc (file permissions),
    inproc, or tcp on a loopback address."""
    transport, host, _ = parse_endpoint(endpoint)
    return transport != "tcp" or is_loopback_host(host)


def who_reaches(local: bool, where: str) -> str:
    """The "who can reach it" half of a start-up endpoint line."""
    return "this machine only" if local else f"any host that can reach {where}"


def check_token(token: str) -> None:
    """Raise ValueError unless ``token`` is a usable show-control token."""
    if not TOKEN_MIN_CHARS <= len(token) <= TOKEN_MAX_CHARS:
        raise ValueError(
            f"a token has {TOKEN_MIN_CHARS}-{TOKEN_MAX_CHARS} characters; "
            f"got {len(token)}"
        )
    if not set(token) <= _TOKEN_CHARS:
        raise ValueError("a token uses only A-Z a-z 0-9 - _")


# ---- CURVE keys ----------------------------------------------------------------------


def write_keypair(folder: str | Path, name: str) -> tuple[Path, Path]:
    """Write ``NAME.key`` (public) and ``NAME.key_secret`` (public + secret), 0600.

    Raises:
        KeyFileError: a file exists already, or the name is not a plain file name.
        OSError: the folder cannot be written.
    """
    if not name or "/" in name or name.startswith("."):
        raise KeyFileError(f"a key name is a plain file name; got {name!r}")
    folder = Path(folder)
    public_key, secret_key = zmq.curve_keypair()
    public_path = folder / f"{name}.key"
    secret_path = folder / f"{name}.key_secret"
    for path in (public_path, secret_path):
        if path.exists():
            raise KeyFileError(f"{path}: exists already (not overwritten)")
    head = "#   ZeroMQ CURVE certificate written by retargetd keys\n"
    public_text = (
        f"{head}#   public key of {name}: give it to the peer\n"
        f'metadata\ncurve\n    public-key = "{public_key.decode()}"\n'
    )
    secret_text = (
        f"{head}#   SECRET key of {name}: keep it (mode 0600)\n"
        f'metadata\ncurve\n    public-key = "{public_key.decode()}"\n'
        f'    secret-key = "{secret_key.decode()}"\n'
    )
    for path, text in ((public_path, public_text), (secret_path, secret_text)):
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as f:
            f.write(text)
    return public_path, secret_path


def load_public_key(path: str | Path) -> bytes:
    """The Z85 public key of a ``.key`` (or ``.key_secret``) file.

    Raises:
        KeyFileError: missing, unreadable or without a public key.
    """
    try:
        public_key, _ = load_certificate(path)
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise KeyFileError(f"{path}: not a key file: {exc}") from None
    if len(public_key) != 40:
        raise KeyFileError(f"{path}: the public key is not 40 Z85 characters")
    return public_key


def load_secret_key(path: str | Path) -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys of a ``.key_secret`` file that only its owner can
    read.

    Raises:
        KeyFileError: missing, readable by group or others, or without a secret key.
    """
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise KeyFileError(f"{path}: cannot read key file: {exc.strerror}") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise KeyFileError(
            f"{path}: a secret key must be readable by its owner only "
            f"(chmod 600); mode is {stat.S_IMODE(mode):o}"
        )
    public_key = load_public_key(path)
    _, secret_key = load_certificate(path)
    if secret_key is None or len(secret_key) != 40:
        raise KeyFileError(f"{path}: no secret key (a .key_secret file is needed)")
    return public_key, secret_key


# ---- HMAC keys (signed marker datagrams) -----------------------------------------

#: A key file larger than this is not one (a key line and a few comment lines).
_HMAC_FILE_MAX_BYTES = 4096


def write_hmac_key(folder: str | Path, name: str) -> Path:
    """Write ``NAME.hmac``: 32 random bytes (``secrets``) as hex, mode 0600.

    Raises:
        KeyFileError: the file exists already, or the name is not a plain file name.
        OSError: the folder cannot be written.
    """
    if not name or "/" in name or name.startswith("."):
        raise KeyFileError(f"a key name is a plain file name; got {name!r}")
    path = Path(folder) / f"{name}.hmac"
    text = (
        "# HMAC-SHA256 key of retargetd's signed marker datagrams (PROTOCOLS.md 13):\n"
        f"# SECRET: give it to the sender {name} over a safe channel; mode 0600\n"
        f"{secrets.token_hex(KEY_MIN_BYTES)}\n"
    )
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise KeyFileError(f"{path}: exists already (not overwritten)") from None
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(text)
    return path


def load_hmac_key(path: str | Path) -> bytes:
    """The key bytes of an HMAC key file that only its owner can read.

    Raises:
        KeyFileError: missing, readable by group or others, too large, or not one
            line of 64-128 hex digits (besides ``#`` comments).
    """
    try:
        st = os.stat(path)
    except OSError as exc:
        raise KeyFileError(f"{path}: cannot read key file: {exc.strerror}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise KeyFileError(
            f"{path}: a key must be readable by its owner only (chmod 600); mode is "
            f"{stat.S_IMODE(st.st_mode):o}"
        )
    if st.st_size > _HMAC_FILE_MAX_BYTES:
        raise KeyFileError(f"{path}: not a key file (over {_HMAC_FILE_MAX_BYTES} B)")
    try:
        with open(path, "rb") as f:
            text = f.read(_HMAC_FILE_MAX_BYTES + 1).decode("utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise KeyFileError(f"{path}: cannot read key file: {exc}") from None
    lines = [ln.strip() for ln in text.splitlines()]
    keys = [ln for ln in lines if ln and not ln.startswith("#")]
    want = f"one line of {2 * KEY_MIN_BYTES}-{2 * KEY_MAX_BYTES} hex digits"
    if len(keys) != 1:
        raise KeyFileError(f"{path}: expected {want}; found {len(keys)} lines")
    try:
        key = bytes.fromhex(keys[0])
        check_key(key)
    except ValueError:
        raise KeyFileError(f"{path}: expected {want}") from None
    return key


def osc_verifier(key_file: str) -> DatagramVerifier | None:
    """The OSC input's verifier of signed datagrams (None: ``key_file`` unset).

    Raises:
        KeyFileError: see :func:`load_hmac_key`.
    """
    return DatagramVerifier(load_hmac_key(key_file)) if key_file else None


def unauthenticated_warning(input_name: str, where: str, keys: str) -> str:
    """The start-up line of a marker input off loopback without a key."""
    fix = (
        "[input.osc] key_file (retargetd keys --hmac NAME; PROTOCOLS.md 13)"
        if input_name == "osc"
        else f"[input.zmq] secret_key and {keys} (CURVE; retargetd keys NAME)"
    )
    return (
        f"warning: {input_name} markers at {where} are not authenticated: any host "
        f"that can reach it can move the avatar; set {fix}"
    )


class _AllowedKeys:
    """ZAP credentials provider: a client is let in when its key is listed."""

    def __init__(self, keys: frozenset[bytes]) -> None:
        self.keys = keys

    def callback(self, domain: str, key: bytes) -> bool:
        """Called by the authenticator thread with the client's Z85 key."""
        return key in self.keys


class CurveGuard:
    """A private ZeroMQ context with a ZAP authenticator thread that lets in only
    the listed client keys; CURVE server sockets of the daemon are made here.

    Args:
        name: what the guard protects (log and thread name).
    """

    def __init__(self, name: str) -> None:
        from zmq.auth.thread import ThreadAuthenticator

        self.name = name
        self.ctx: Any = zmq.Context()
        self._auth = ThreadAuthenticator(self.ctx, log=None)
        self._auth.start()
        self._providers: dict[str, _AllowedKeys] = {}

    def server_socket(
        self, kind: int, secret_key_file: str, client_key_files: tuple[str, ...]
    ) -> Any:
        """A socket of ``kind`` that is a CURVE server with the daemon's key and lets
        in the listed clients only (ZAP domain per socket)."""
        public_key, secret_key = load_secret_key(secret_key_file)
        allowed = frozenset(load_public_key(p) for p in client_key_files)
        domain = f"retargetd-{len(self._providers)}"
        provider = _AllowedKeys(allowed)
        self._providers[domain] = provider
        self._auth.configure_curve_callback(
            domain=domain, credentials_provider=provider
        )
        sock = self.ctx.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.curve_secretkey = secret_key
        sock.curve_publickey = public_key
        sock.curve_server = True
        sock.zap_domain = domain.encode()
        return sock

    def close(self) -> None:
        """Stop the authenticator and end the context (its sockets closed first)."""
        self._auth.stop()
        self.ctx.term()


def curve_client(sock: Any, key_file: str | Path, server_key_file: str | Path) -> None:
    """Make ``sock`` a CURVE client with its secret key file and the server's public
    key (before ``connect``)."""
    public_key, secret_key = load_secret_key(key_file)
    sock.curve_secretkey = secret_key
    sock.curve_publickey = public_key
    sock.curve_serverkey = load_public_key(server_key_file)
