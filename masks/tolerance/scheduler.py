"""A remote dask scheduler address: parsed, then probed within a bounded time before dask connects.

dask.distributed's client trusts its peer: after the TCP connection it waits for the
scheduler's handshake without a time limit (a server that accepts and never answers holds
``doe tolerance`` forever) and reads the first 8 bytes as the length of the frames to
allocate (an HTTP server's ``HTTP/1.1`` reads as 3 EiB). The probe here speaks the first
step of that protocol itself: a dask scheduler writes its handshake as soon as a connection
opens (``distributed.comm.core.Listener.on_connection``), an 8-byte little-endian length
and that many bytes of msgpack. Anything else within :data:`PROBE_TIMEOUT_S` is refused as
one line before dask is asked to connect. ``tls://`` addresses are only checked for a
listening port (their handshake starts with the client's TLS hello).
"""

from __future__ import annotations

import re
import socket
import struct
import time

from doedesign.errors import DoeError

__all__ = ["MAX_HANDSHAKE_BYTES", "PROBE_TIMEOUT_S", "parse_address", "probe_scheduler"]

#: Whole time allowed for connecting and reading the scheduler's handshake (s).
PROBE_TIMEOUT_S = 20.0
# A scheduler's handshake is a few hundred bytes of msgpack; more is not a dask scheduler.
MAX_HANDSHAKE_BYTES = 1 << 20
_ADDRESS = re.compile(r"(?P<scheme>tcp|tls)://(?:\[(?P<ip6>[0-9A-Fa-f:.]+)\]|(?P<host>[A-Za-z0-9._-]+)):(?P<port>\d{1,5})/?")


def parse_address(address: str) -> tuple[str, str, int]:
    """``(scheme, host, port)`` of ``tcp://HOST:PORT`` or ``tls://HOST:PORT`` (IPv6 hosts in brackets).

    Raises
    ------
    DoeError
        Anything else, as one line.
    """
    m = _ADDRESS.fullmatch(address.strip())
    port = int(m["port"]) if m else 0
    if not m or not 0 < port < 65536:
        raise DoeError(f"--scheduler {address!r}: not a scheduler address; give tcp://HOST:PORT "
                       "(PORT 1 to 65535) or tls://HOST:PORT")
    return m["scheme"], m["ip6"] or m["host"], port


def probe_scheduler(address: str, timeout_s: float | None = None) -> None:
    """Check within ``timeout_s`` (default :data:`PROBE_TIMEOUT_S`) that a dask scheduler answers at ``address``.

    Raises
    ------
    DoeError
        No connection, no handshake in time, or a peer that does not speak dask (one line).
    """
    timeout_s = PROBE_TIMEOUT_S if timeout_s is None else timeout_s
    scheme, host, port = parse_address(address)
    deadline = time.monotonic() + timeout_s
    what = f"--scheduler {address}"
    try:
        sock = socket.create_connection((host, port), timeout=timeout_s)
    except socket.timeout:
        raise DoeError(f"{what}: no connection within {timeout_s:g} s") from None
    except OSError as exc:
        raise DoeError(f"{what}: cannot connect ({exc.strerror or exc})") from None
    with sock:
        if scheme == "tls":
            return
        try:
            header = _read(sock, 8, deadline)
            (length,) = struct.unpack("<Q", header)
            if not 0 < length <= MAX_HANDSHAKE_BYTES:
                raise DoeError(f"{what}: the server there is not a dask scheduler (its first bytes "
                               f"{header!r} announce {length} bytes, not a handshake)")
            _read(sock, length, deadline)
        except socket.timeout:
            raise DoeError(f"{what}: accepted the connection but sent no dask handshake within "
                           f"{timeout_s:g} s (not a dask scheduler, or not answering)") from None
        except ConnectionError as exc:
            raise DoeError(f"{what}: closed the connection during the dask handshake ({exc}); "
                           "not a dask scheduler?") from None
        except OSError as exc:
            raise DoeError(f"{what}: handshake failed ({exc.strerror or exc})") from None


def _read(sock, n, deadline):
    data = bytearray()
    while len(data) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise socket.timeout
        sock.settimeout(left)
        chunk = sock.recv(min(n - len(data), 65536))
        if not chunk:
            raise ConnectionError(f"closed after {len(data)} of {n} bytes")
        data += chunk
    return bytes(data)
