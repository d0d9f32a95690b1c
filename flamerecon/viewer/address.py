"""Where the viewer listens, checked before viser starts, and viser started so that it cannot hang.

viser binds in a thread of its own, trying the next port on any ``OSError`` and waiting, in the
thread that made it, for that thread to say it listens: a port past 65535 (``OverflowError``), a
host that does not resolve or is no address of this machine (an ``OSError`` on 1000 ports in
turn) ended that thread and left the caller waiting for ever. So the host and port are checked
here first (:func:`listen_address`: a port in 1-65535, a host that resolves to a wildcard or an
address of this machine, the first free port from the one asked for), each refusal one line
naming the option; then :func:`start_viser` makes the server in a helper thread and waits for it
in steps, so that a failure in viser's thread is one :class:`~flamerecon.errors.ConfigError` and
a stop signal is acted on at once.
"""

from __future__ import annotations

import contextlib
import errno
import socket
import threading
import time
from dataclasses import dataclass

from flamerecon.errors import ConfigError

#: the largest TCP port
MAX_PORT = 65535
#: ports tried from the one asked for, the next when one is taken (viser's own count)
PORT_TRIES = 1000
#: seconds viser may take to listen once its port and host are known to be free (it takes
#: milliseconds); past them the start is a failure, not a wait
START_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class Fields:
    """The names the host and port go by in messages: ``--host``/``--port`` on the command line,
    ``view.host``/``view.port`` in ``fr.view``."""

    host: str = "--host"
    port: str = "--port"


#: the names on the command line
COMMAND_LINE = Fields()


def _addresses(host: str, fields: Fields) -> list[tuple]:
    """(family, sockaddr) of every address ``host`` resolves to, for a server socket."""
    if not isinstance(host, str) or "\0" in host:
        raise ConfigError(f"{fields.host}: got {host!r}; give an address of this machine such as 127.0.0.1, or "
                          "0.0.0.0 for every network")
    try:
        found = socket.getaddrinfo(host or None, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as err:
        raise ConfigError(f"{fields.host}: '{host}' does not resolve ({getattr(err, 'strerror', None) or err}); "
                          "give an address of this machine (127.0.0.1, the default, serves this machine only; "
                          "0.0.0.0 every network)") from None
    return list(dict.fromkeys((family, sockaddr) for family, _, _, _, sockaddr in found))


def _bind(family: int, sockaddr: tuple, port: int) -> None:
    """Bind a listening socket as asyncio's server does (``SO_REUSEADDR``) to ``sockaddr`` at
    ``port``, then close it; the ``OSError`` of a failure."""
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if family == socket.AF_INET6:
            with contextlib.suppress(OSError):
                probe.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
        probe.bind((sockaddr[0], port, *sockaddr[2:]))
        probe.listen(1)


def check_port(port, fields: Fields = COMMAND_LINE) -> int:
    """``port`` when it is a whole number in 1-65535, else a ConfigError naming ``fields.port``."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= MAX_PORT:
        raise ConfigError(f"{fields.port}: got {port!r}; a port is a whole number from 1 to {MAX_PORT} "
                          "(8080, the default, or another above 1023)")
    return port


def listen_address(host: str, port: int, fields: Fields = COMMAND_LINE) -> int:
    """The port to serve ``host`` on: ``port`` or the first free one after it (at most
    :data:`PORT_TRIES` tried, none past 65535), every address ``host`` resolves to bound there.
    A ConfigError names the option at fault: a port out of range, a host that does not resolve,
    that is not an address of this machine (a wildcard, 0.0.0.0 or ::, always is), a port
    this user may not take (below 1024 without root) or no free port in the range."""
    check_port(port, fields)
    addresses = _addresses(host, fields)
    for family, sockaddr in addresses:
        try:
            _bind(family, sockaddr, 0)
        except OSError as err:
            if err.errno == errno.EADDRNOTAVAIL:
                raise ConfigError(f"{fields.host}: '{host}' ({sockaddr[0]}) is not an address of this machine; give "
                                  "one of its own (127.0.0.1, the default; its name or a network address it has), "
                                  "or 0.0.0.0 for every network") from None
            raise ConfigError(f"{fields.host}: cannot listen on '{host}' ({sockaddr[0]}): {err.strerror or err}; "
                              "give another address (127.0.0.1, the default)") from None
    last = min(MAX_PORT, port + PORT_TRIES - 1)
    for candidate in range(port, last + 1):
        try:
            for family, sockaddr in addresses:
                _bind(family, sockaddr, candidate)
        except OSError as err:
            if err.errno == errno.EADDRINUSE:
                continue
            if err.errno == errno.EACCES:
                raise ConfigError(f"{fields.port}: {candidate} may not be taken by this user (ports below 1024 "
                                  "need root); choose a port above 1023 (8080, the default)") from None
            raise ConfigError(f"{fields.port}: cannot listen on {host}:{candidate}: {err.strerror or err}; choose "
                              "another port") from None
        return candidate
    raise ConfigError(f"{fields.port}: every port from {port} to {last} is taken on {host}; choose another "
                      f"{fields.port} (8080, the default, moves to the next free one)")


def start_viser(viser, host: str, port: int, fields: Fields = COMMAND_LINE, timeout: float = START_TIMEOUT_S):
    """``viser.ViserServer(host, port)`` (quiet, labelled flamerecon), made in a helper thread
    while this one waits in steps of 0.1 s: a stop signal raises here as it arrives, and an
    exception in viser's own server thread (its bind), an exception of the constructor or no
    server after ``timeout`` seconds is a ConfigError naming the address (the helper thread, stuck
    in viser's wait, is a daemon and dies with the process)."""
    made: dict = {}
    failed: list[BaseException] = []
    done = threading.Event()
    previous_hook = threading.excepthook

    def record(args) -> None:  # an exception that ends a thread while viser starts: viser's bind
        if args.exc_type is SystemExit:
            return
        failed.append(args.exc_value)

    def make() -> None:
        try:
            made["server"] = viser.ViserServer(host=host, port=port, label="flamerecon", verbose=False)
        except BaseException as err:  # noqa: BLE001 - handed to the waiting thread
            failed.append(err)
        finally:
            done.set()

    threading.excepthook = record
    try:
        threading.Thread(target=make, name="flamerecon-view-start", daemon=True).start()
        end = time.monotonic() + timeout
        while not done.wait(0.1):
            if failed or time.monotonic() > end:
                break
    finally:
        threading.excepthook = previous_hook
    if "server" in made:
        return made["server"]
    why = (f"{type(failed[0]).__name__}: {' '.join(str(failed[0]).split())}" if failed
           else f"no server after {timeout:.0f} s")
    raise ConfigError(f"{fields.host}/{fields.port}: viser could not listen on {host}:{port} ({why}); choose "
                      f"another {fields.port} or {fields.host} (127.0.0.1 and 8080 are the defaults)")
