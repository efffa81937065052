"""Check that ``dask_address`` is a Dask scheduler before a Dask client connects to it.

``distributed.Client`` trusts what answers at the address: a web server's reply
``HTTP/1.0 ...`` read as a Dask frame header asks for 3.07 EiB, and an address that
accepts connections but never answers keeps it waiting. :func:`check_scheduler` opens a
plain TCP connection with a timeout and reads the handshake a Dask scheduler sends as
soon as it accepts a connection: a little-endian uint64 message length (tens of bytes),
then a frame count, the frame lengths and a msgpack mapping that names
``pickle-protocol``. Anything else is refused in one line naming the address.
"""

from __future__ import annotations

import socket
import struct
import time

from .errors import SpecError

__all__ = ["CONNECT_TIMEOUT_S", "MAX_HANDSHAKE_BYTES", "check_scheduler"]

CONNECT_TIMEOUT_S = 10.0
"""Seconds to wait for the scheduler to accept the connection, and again for its handshake."""
MAX_HANDSHAKE_BYTES = 65_536
"""Longest handshake accepted (a scheduler's is about 60 bytes)."""


def check_scheduler(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Refuse an address where no Dask scheduler speaks Dask's TCP protocol.

    Only ``tcp://host:port`` addresses are probed (the protocol of ``dask scheduler``);
    other protocols (``tls://``, ``ws://``, ...) are left to ``distributed.Client``.

    Args:
        address: the spec's ``dask_address``, e.g. ``"tcp://10.0.0.5:8786"``.
        timeout_s: seconds for the connection, and again for the handshake.

    Raises:
        SpecError: the host does not resolve, the connection is refused or times out,
            or what answers does not send a Dask handshake within ``timeout_s`` (one
            line naming ``dask_address`` and the address).
    """
    if not address.startswith("tcp://"):
        return
    host, _, port = address[len("tcp://"):].rpartition(":")
    host = host.strip("[]")  # tcp://[::1]:8786
    where = f"dask_address: {address!r}"
    nothing = f"dask_address: no Dask scheduler answers at {address!r}"
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise SpecError(f"{where}: expected tcp://host:port")
    start = time.monotonic()
    connected = False
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s) as conn:
            connected = True
            conn.settimeout(timeout_s)
            head = _read(conn, 8)
            (length,) = struct.unpack("<Q", head)
            if not 16 <= length <= MAX_HANDSHAKE_BYTES:
                raise SpecError(f"{where} is not a Dask scheduler (it answered {head!r}, not a Dask handshake)")
            body = _read(conn, length)
    except socket.timeout:
        waited = time.monotonic() - start
        if connected:  # a web server waits for a request, a Dask scheduler speaks first
            raise SpecError(f"{where} is not a Dask scheduler (it accepted the connection but sent no Dask "
                            f"handshake within {timeout_s:g} s)") from None
        raise SpecError(f"{nothing} (no connection within {waited:.0f} s: "
                        "unreachable?)") from None
    except (OSError, EOFError) as exc:
        reason = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
        raise SpecError(f"{nothing} ({reason})") from None
    if b"pickle-protocol" not in body:
        raise SpecError(f"{where} is not a Dask scheduler (its first message is not a Dask handshake)")


def _read(conn: socket.socket, n: int) -> bytes:
    """Exactly ``n`` bytes from ``conn``; EOFError if it closes first (socket.timeout as set on it)."""
    data = bytearray()
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        if not chunk:
            raise EOFError(f"the connection closed after {len(data)} bytes")
        data += chunk
    return bytes(data)
