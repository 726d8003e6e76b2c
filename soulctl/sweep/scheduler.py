"""``--scheduler ADDRESS``: the address of an existing Dask scheduler, checked before anything
runs or is created.

Accepted: ``tcp://HOST:PORT`` (or ``HOST:PORT``), HOST a name, an IPv4 address or an IPv6
address in brackets.  Other Dask transports are refused: ``tls://`` needs certificates and
``ucx://`` an optional transport, and soulctl has no options for either (tunnel the
scheduler's port over SSH instead); ``inproc://`` only exists inside one Python process.

``probe`` then checks that a Dask scheduler answers there, within ``CONNECT_TIMEOUT_S`` for
everything (name resolution, connection, the scheduler's greeting): Dask's own connection
waits without a bound for a listener that accepts the connection but never speaks (an HTTP
server, such as the scheduler's dashboard port) and believes whatever length a listener that
answers something else announces (it then tries to allocate it).  The probe reads at most
``MAX_GREETING_BYTES``, checks that they are Dask's handshake, answers with soulctl's own
handshake (so that the scheduler logs no broken connection) and closes.  It runs in a daemon
thread, so that nothing lingers at exit when it gives up.
"""

from __future__ import annotations

import pickle
import re
import socket
import struct
import sys
import threading
import time

from ..errors import InputError

CONNECT_TIMEOUT_S = 10.0  # the whole probe, and then Dask's own connection
MAX_GREETING_BYTES = 4096  # a Dask handshake is ~60 bytes
_ADDRESS = re.compile(r"(?:(?P<scheme>[A-Za-z][A-Za-z0-9+.-]*)://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):(?P<port>[0-9]+)")
FORM = "tcp://HOST:PORT"


def parse_address(address: str) -> tuple[str, int]:
    """(host, port) of a ``--scheduler`` address (see the module); InputError otherwise."""
    text = address.strip()
    scheme = text.split("://", 1)[0].lower() if "://" in text else "tcp"
    if scheme != "tcp":
        why = {
            "tls": "TLS needs certificates soulctl has no options for; tunnel the scheduler's port over SSH instead",
            "ucx": "UCX is an optional transport soulctl has no options for",
            "inproc": "inproc:// only exists inside one Python process",
        }.get(scheme, "not a Dask transport")
        raise InputError(f"--scheduler must be {FORM}, got '{address}' ({scheme}://: {why})")
    m = _ADDRESS.fullmatch(text)
    port = int(m["port"]) if m else 0
    if not m or not 1 <= port <= 65535:
        raise InputError(f"--scheduler must be {FORM} (PORT 1..65535; an IPv6 HOST in brackets), got '{address}'")
    host = m["host"][1:-1] if m["host"].startswith("[") else m["host"]
    return host, port


def normal_address(address: str) -> str:
    host, port = parse_address(address)
    return f"tcp://[{host}]:{port}" if ":" in host else f"tcp://{host}:{port}"


def probe(address: str, timeout: float | None = None) -> str:
    """Check that a Dask scheduler answers at ``address`` within ``timeout`` s (default
    ``CONNECT_TIMEOUT_S``; see the module); the address as Dask takes it, or an InputError
    naming it."""
    host, port = parse_address(address)
    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    result: dict = {}
    thread = threading.Thread(target=_probe, args=(host, port, timeout, result), daemon=True, name="soulctl-scheduler-probe")
    thread.start()
    thread.join(timeout)
    error = result.get("error", f"no answer from a Dask scheduler within {timeout:g} s")
    if not result.get("ok"):
        raise InputError(f"cannot reach the Dask scheduler at {address}: {error}; nothing was run")
    return normal_address(address)


def _probe(host: str, port: int, timeout: float, result: dict) -> None:
    try:
        _greet(host, port, time.monotonic() + timeout)
        result["ok"] = True
    except socket.gaierror as e:
        result["error"] = f"unknown host {host} ({e.strerror})"
    except ConnectionRefusedError:
        result["error"] = "connection refused (no scheduler listens on that port)"
    except TimeoutError:
        result["error"] = f"no answer from a Dask scheduler within {timeout:g} s"
    except _NotDask as e:
        result["error"] = f"the listener there is not a Dask scheduler ({e})"
    except OSError as e:
        result["error"] = e.strerror or str(e)
    except Exception as e:  # noqa: BLE001 - whatever the peer sent, it is the address's fault
        result["error"] = f"the listener there is not a Dask scheduler ({type(e).__name__})"


class _NotDask(Exception):
    pass


def _left(deadline: float) -> float:
    left = deadline - time.monotonic()
    if left <= 0:
        raise TimeoutError()
    return left


def _recv(sock: socket.socket, n: int, deadline: float) -> bytes:
    data = b""
    while len(data) < n:
        sock.settimeout(_left(deadline))
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise _NotDask("it closed the connection without a handshake")
        data += chunk
    return data


def _greet(host: str, port: int, deadline: float) -> None:
    """Dask's TCP handshake: the server speaks first, an 8-byte length, then its frames
    (8-byte count, 8-byte lengths, a msgpack map)."""
    import msgpack  # Dask's own dependency

    with socket.create_connection((host, port), timeout=_left(deadline)) as sock:
        (n,) = struct.unpack("Q", _recv(sock, 8, deadline))
        if not 16 <= n <= MAX_GREETING_BYTES:
            raise _NotDask(f"it announced a first message of {n} bytes")
        body = _recv(sock, n, deadline)
        count, length = struct.unpack_from("QQ", body)
        if count < 1 or 16 + 8 * (count - 1) + length > n:
            raise _NotDask("its first message is not Dask's frames")
        start = 8 + 8 * count
        info = msgpack.loads(body[start : start + length])
        if not isinstance(info, dict) or "python" not in info:
            raise _NotDask("its first message is not Dask's handshake")
        reply = msgpack.dumps({"compression": None, "python": list(sys.version_info[:3]), "pickle-protocol": pickle.HIGHEST_PROTOCOL})
        frames = struct.pack("QQ", 1, len(reply)) + reply
        sock.settimeout(_left(deadline))
        sock.sendall(struct.pack("Q", len(frames)) + frames)
