"""Who may talk to a cell: loopback and ``ipc://`` stay keyless; any other address needs
ZeroMQ CURVE keys on both sides (encryption, and only controllers holding a key the cell
knows get through).

One folder of keys serves both sides (``dlo keys --out DIR``): the cell reads
``cell.key_secret`` and lets in the public keys ``*.key`` beside it; a controller reads
``controller.key_secret`` and ``cell.key`` (so it talks to this cell and no other). Copy the
folder to the controller's machine, or only the two files it reads.
"""

from __future__ import annotations

import ipaddress
import os
import socket
from pathlib import Path
from typing import Any

from dlocli.errors import BadInput

CELL, CONTROLLER = "cell", "controller"


def host_of(address: str) -> str | None:
    """The host of a tcp:// address (None for ipc://)."""
    if not address.startswith("tcp://"):
        return None
    return address[len("tcp://") :].rsplit(":", 1)[0]


def is_loopback(address: str) -> bool:
    """Whether only this machine can reach ``address``: ipc://, or a tcp host that is a
    loopback address or resolves to loopback addresses only (``*``, 0.0.0.0 and interface
    names are not)."""
    host = host_of(address)
    if host is None:
        return True
    if host in ("*", ""):
        return False
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        pass
    try:
        found = socket.getaddrinfo(host, None)
    except (OSError, UnicodeError):
        return False  # an interface name (eth0) or a name that does not resolve
    return bool(found) and all(ipaddress.ip_address(a[4][0]).is_loopback for a in found)


#: the other side's keys flag, by this side's: the cell (`dlo serve`, a robot cell) takes the
#: folder as --keys, the controller as --cell-keys
OTHER_SIDE = {
    "--keys": "the same folder as --cell-keys DIR to the controller (`dlo control`)",
    "--cell-keys": "the same folder as --keys DIR to the cell (`dlo serve`)",
}


def require_keys_off_loopback(address: str, keys: Path | None, flag: str, keys_flag: str) -> None:
    """BadInput if ``address`` is reachable from other machines and no keys were given."""
    if keys is None and not is_loopback(address):
        raise BadInput(
            f"{flag} {address} is reachable from other machines: a cell off loopback needs "
            f"CURVE keys; make them with `dlo keys --out DIR`, pass {keys_flag} DIR here and "
            f"{OTHER_SIDE[keys_flag]} (or use tcp://127.0.0.1:PORT or ipc://PATH on one machine)"
        )


def make_keys(folder: Path) -> list[Path]:
    """Write a cell's and a controller's key pair into the new folder ``folder``; the files
    written. Secret files are readable by their owner only."""
    import zmq

    if folder.exists() and any(folder.iterdir()):
        raise BadInput(f"{folder} is not empty: pass a new folder for the keys")
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for name in (CELL, CONTROLLER):
        public, secret = zmq.curve_keypair()
        written.append(_write_key(folder / f"{name}.key", public, None))
        written.append(_write_key(folder / f"{name}.key_secret", public, secret))
    return written


def _write_key(path: Path, public: bytes, secret: bytes | None) -> Path:
    # the ZPL certificate form zmq.auth reads (zmq.auth.load_certificate)
    lines = ["#   ZeroMQ CURVE certificate, written by `dlo keys`", "metadata", "curve"]
    lines.append(f'    public-key = "{public.decode()}"')
    if secret is not None:
        lines.append(f'    secret-key = "{secret.decode()}"')
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600 if secret else 0o644)
    with os.fdopen(fd, "w") as f:
        f.write("\n".join(lines) + "\n")
    os.replace(tmp, path)
    return path


def _load(folder: Path, name: str, secret: bool, flag: str) -> tuple[bytes, bytes | None]:
    import zmq.auth

    path = folder / (f"{name}.key_secret" if secret else f"{name}.key")
    if not path.is_file():
        raise BadInput(
            f"{flag} {folder}: no {path.name} there; make the keys with `dlo keys --out {folder}`"
        )
    mode = path.stat().st_mode & 0o777
    if secret and mode & 0o077:  # as ssh refuses a private key others can read
        raise BadInput(
            f"{flag} {folder}: {path.name} is readable by others (mode {mode:o}), and it is "
            f"a secret key: run `chmod 600 {path}` (and make new keys if others may have "
            "read it)"
        )
    try:
        public, secret_key = zmq.auth.load_certificate(path)
    except (OSError, ValueError, KeyError) as exc:
        raise BadInput(f"{flag} {folder}: {path.name} is not a CURVE key file ({exc})") from None
    if not public or (secret and not secret_key):
        raise BadInput(f"{flag} {folder}: {path.name} holds no {'secret' if secret else ''} key")
    return public, secret_key


def secure_cell(context: Any, socket_: Any, folder: Path) -> Any:
    """Make ``socket_`` a CURVE server that lets in the public keys in ``folder``; returns
    the authenticator (stop it when done)."""
    from zmq.auth.thread import ThreadAuthenticator

    public, secret = _load(folder, CELL, True, "--keys")
    _load(folder, CONTROLLER, False, "--keys")  # a folder with no controller key lets no one in
    authenticator = ThreadAuthenticator(context)
    authenticator.start()
    authenticator.configure_curve(domain="*", location=str(folder))
    socket_.curve_secretkey, socket_.curve_publickey = secret, public
    socket_.curve_server = True
    return authenticator


def secure_controller(socket_: Any, folder: Path) -> None:
    """Make ``socket_`` a CURVE client holding the controller's keys, talking to the cell
    whose public key is in ``folder``."""
    public, secret = _load(folder, CONTROLLER, True, "--cell-keys")
    cell_public, _ = _load(folder, CELL, False, "--cell-keys")
    socket_.curve_secretkey, socket_.curve_publickey = secret, public
    socket_.curve_serverkey = cell_public
