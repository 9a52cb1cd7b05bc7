"""CURVE keys for ZeroMQ links (docs/protocol.md, "Security").

A key directory holds two key pairs in ZeroMQ's certificate format (readable by
``zmq.auth.load_certificate``), every file created with mode 0600 and the
directory with 0700::

    server.key_secret   the server's public + secret key (the supervisor side)
    client.key_secret   the client's public + secret key (the ground side)
    server.key          the server's public key (all a client needs of the server)
    clients/client.key  the public keys the server accepts, one file per client

:func:`generate_keys` writes a fresh directory (``hazard-hil run`` does this
once per run, under the run's output directory). Generate keys with
``hazard-hil keys DIR`` (or ``python -m protocol.zmqauth DIR``) to connect your own peer.
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

from protocol.errors import InputError

_HEADER = "#   ZeroMQ CURVE certificate (hazard-hil); keep *_secret files private\n\nmetadata\ncurve\n"


def _write(path: Path, public: bytes, secret: bytes | None) -> None:
    text = _HEADER + f'    public-key = "{public.decode("ascii")}"\n'
    if secret is not None:
        text += f'    secret-key = "{secret.decode("ascii")}"\n'
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)  # never world-readable, not even briefly
    with os.fdopen(fd, "w") as fh:
        fh.write(text)


def generate_keys(directory: str | Path) -> Path:
    """Create ``directory`` (must not exist or be empty) with a server and a client key pair."""
    import zmq

    if not str(directory).strip():  # Path("") is the current directory: the keys would land among the user's files
        raise InputError("key directory must name a path, got an empty one")
    d = Path(directory)
    if d.exists() and not d.is_dir():
        raise InputError(f"key directory {d} is a file, not a directory")
    if d.exists() and any(d.iterdir()):
        raise InputError(f"key directory {d} is not empty; refusing to overwrite keys")
    made = not d.exists()
    try:
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.chmod(d, 0o700)
        (d / "clients").mkdir(mode=0o700, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create key directory {d}: {exc.strerror or exc}") from None
    s_pub, s_sec = zmq.curve_keypair()
    c_pub, c_sec = zmq.curve_keypair()
    files = [
        (d / "server.key_secret", s_pub, s_sec),
        (d / "server.key", s_pub, None),
        (d / "client.key_secret", c_pub, c_sec),
        (d / "clients" / "client.key", c_pub, None),
    ]
    try:
        for path, pub, sec in files:
            _write(path, pub, sec)
    except BaseException as exc:
        # a full disk left a 0-byte secret key, and the directory, no longer empty, was refused on the next try
        # (QA of stop 72): what this call made goes, and the user is told the directory is as it was
        for path, _, _ in files:
            path.unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            (d / "clients").rmdir()
        if made:  # an empty directory that was there before stays
            with contextlib.suppress(OSError):
                d.rmdir()
        if isinstance(exc, OSError):
            raise InputError(f"cannot write the keys in {d}: {exc.strerror or exc}; nothing was left there") from None
        raise
    return d


def _load(path: Path, need_secret: bool) -> tuple[bytes, bytes | None]:
    import zmq.auth

    if path.exists() and not path.is_file():  # a directory, a FIFO: not "missing"
        raise InputError(f"CURVE key file {path} is not a regular file")
    if not path.is_file():
        raise InputError(f"CURVE key file {path} does not exist (create keys with `hazard-hil keys DIR`)")
    mode = path.stat().st_mode & 0o777
    if need_secret and mode & 0o077:  # as ssh refuses an unprotected private key: anyone who reads it is us
        raise InputError(
            f"CURVE secret key file {path} is readable or writable by others (mode {mode:04o}); "
            f"make it private: chmod 600 {path}"
        )
    try:
        pub, sec = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as exc:
        raise InputError(f"CURVE key file {path} is unreadable: {exc}") from None
    if pub is None or (need_secret and sec is None):
        raise InputError(f"CURVE key file {path} lacks a {'secret' if need_secret else 'public'} key")
    return pub, sec


def _private_group(uid: int, gid: int) -> bool:
    """Whether ``gid`` is ``uid``'s user-private group (same name, no other member): under umask 002 (Debian's
    default for such users) a key directory made by hand is group-writable, yet only its owner can write it.
    Debian's sshd accepts the same case."""
    import grp
    import pwd

    try:
        user, group = pwd.getpwuid(uid), grp.getgrgid(gid)
    except KeyError:
        return False
    if user.pw_gid != gid or group.gr_name != user.pw_name or not set(group.gr_mem) <= {user.pw_name}:
        return False
    # a member by another account's primary group is not in gr_mem
    return not any(a.pw_gid == gid and a.pw_uid != uid for a in pwd.getpwall())


def _private_to_its_owner(path: Path, what: str) -> None:
    """Refuse ``path`` when group or others may write it: whoever can drop a public key into ``clients/`` (or
    swap the ground's ``server.key``) is let in, as ssh's StrictModes refuses a writable ``authorized_keys``."""
    try:
        st = path.stat()
    except OSError:
        return  # missing: the loader says so
    mode = st.st_mode & 0o777
    writable = mode & 0o002 or (mode & 0o020 and not _private_group(st.st_uid, st.st_gid))
    if writable:
        fix = "chmod go-w" if path.is_dir() else "chmod 600"
        raise InputError(
            f"{what} {path} can be written by others (mode {mode:04o}): anyone could add or swap a key; "
            f"make it private: {fix} {path}"
        )


def server_keys(directory: str | Path) -> tuple[bytes, bytes, Path]:
    """(public, secret, directory of accepted client public keys) for the binding side."""
    d = Path(directory)
    _private_to_its_owner(d, "CURVE key directory")
    _private_to_its_owner(d / "clients", "CURVE key directory")
    pub, sec = _load(d / "server.key_secret", True)
    assert sec is not None
    clients = d / "clients"
    if not clients.is_dir():
        raise InputError(f"CURVE key directory {d} has no clients/ directory of accepted keys")
    # libzmq's authenticator reads clients/*.key itself, logs a bad one and serves on: no ground could connect
    accepted = sorted(clients.glob("*.key"))
    if not accepted:
        raise InputError(
            f"{clients} holds no accepted public key (*.key): no ground could connect; copy the ground's "
            "client.key there (hazard-hil keys DIR writes one)"
        )
    for path in accepted:
        _private_to_its_owner(path, "accepted CURVE key")
        _load(path, False)
    return pub, sec, clients


def client_keys(directory: str | Path) -> tuple[bytes, bytes, bytes]:
    """(public, secret, server public) for the connecting side."""
    d = Path(directory)
    _private_to_its_owner(d, "CURVE key directory")
    _private_to_its_owner(d / "server.key", "the board's public CURVE key")
    pub, sec = _load(d / "client.key_secret", True)
    server_pub, _ = _load(d / "server.key", False)
    assert sec is not None
    return pub, sec, server_pub


def where_keys_go(d: Path) -> str:
    """Which files of a key directory each side needs, for the line printed after :func:`generate_keys`."""
    return (
        f"CURVE keys written to {d} (mode 0600). The binding side (`hazard-hil flight --keys`, a HIL server) needs "
        "server.key_secret and clients/; the connecting side (`hazard-hil run --flight external --keys`) needs "
        "client.key_secret and server.key. A directory with all four serves both."
    )


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(
        prog="python -m protocol.zmqauth", description="Create DIR with a server and a client CURVE key pair."
    )
    ap.add_argument("dir", type=Path, metavar="DIR", help="a new or empty directory")
    args = ap.parse_args(argv)
    try:
        d = generate_keys(args.dir)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(where_keys_go(d))
    return 0


if __name__ == "__main__":
    sys.exit(main())
