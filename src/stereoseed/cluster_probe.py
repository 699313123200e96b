"""What answers at a ``--scheduler`` address, asked without deserialising anything it sends.

Dask's own ``comm.read()`` decodes a reply with hooks that unpickle what the peer marks as pickled
(``{"__Pickled__": n}``, ``{"__Serialized__": n}``): whatever listens at the address would run code
as the user before anyone looked at what it is. So the pre-flight question ("are you a Dask
scheduler?") is asked here over a plain socket, in Dask's TCP framing, and the reply's first
frame is read with msgpack alone (no object hook, no ext hook: maps, lists, strings and numbers,
nothing that can name a Python object); the other frames, where Dask keeps pickles, are never
decoded. Only an address that answers as a scheduler is handed to Dask's client.

Trust: once the probe has passed, Dask's client and the scheduler exchange pickles by design
(results, errors, the jobs themselves), so the scheduler is trusted as much as the code it runs:
``--scheduler`` is for the cluster's own network (README, "Many sequences, and a cluster").

Dask's TCP framing (distributed.comm.tcp, 2023-2026): a message is ``Q total`` (the bytes of what
follows, up to the last frame read in one go), ``Q nframes``, ``nframes x Q length``, then the
frames; ``Q`` is native byte order, as Dask packs it. After connecting, each side writes its
handshake (a map) and reads the other's; then the client writes ``{"op": ..., "reply": True}`` and
reads the reply.
"""
from __future__ import annotations

import socket
import struct
import sys
import time
from typing import Any

__all__ = ["ask_identity", "ProbeError", "ProbeTimeout", "NotDask"]

_Q = struct.Struct("Q")
# a scheduler's identity lists each worker in a few hundred bytes: 16 MiB is tens of thousands
# of workers, and bounds what a peer that announces a huge message can make this process allocate
MAX_REPLY_BYTES = 16 * 2**20
# a real reply is one or a few frames; a peer announcing more is not worth reading the lengths of
MAX_FRAMES = 1024
_RETRY_S = 0.1  # a refused connection is tried again (a scheduler still starting), as Dask's connect does
_PICKLE_PROTOCOL = 5  # what we announce; nothing is pickled in either direction here


class ProbeError(Exception):
    """Nothing usable answered (refused, closed, not Dask's framing); the text is one line."""


class ProbeTimeout(ProbeError):
    """Something accepted the connection but did not answer within the deadline."""


class NotDask(ProbeError):
    """Something answered, but not in Dask's framing and handshake."""


def ask_identity(address: str, timeout: float) -> Any:
    """Connect to ``address`` (``tcp://HOST:PORT``), do Dask's handshake and ask for its
    identity; return the reply as plain data (a dict for a Dask server: its ``type`` says which).
    The connection is tried until ``timeout`` seconds; the handshake then gets the same again.
    Raises :class:`ProbeTimeout`, :class:`NotDask` or :class:`ProbeError`; ValueError for an address that is not
    ``tcp://HOST:PORT``."""
    host, port = _host_port(address)
    sock = _connect(host, port, time.monotonic() + timeout)
    deadline = time.monotonic() + timeout
    try:
        _send(sock, {"compression": None, "python": tuple(sys.version_info)[:3], "pickle-protocol": _PICKLE_PROTOCOL})
        handshake = _receive(sock, deadline)
        if not isinstance(handshake, dict) or "pickle-protocol" not in handshake:
            raise NotDask("it did not answer Dask's handshake")
        _send(sock, {"op": "identity", "reply": True})
        return _receive(sock, deadline)
    finally:
        sock.close()


def _host_port(address: str) -> tuple[str, int]:
    """HOST and PORT of ``tcp://HOST:PORT`` (or ``HOST:PORT``, which Dask reads as tcp;
    ``[::1]`` for an IPv6 host)."""
    scheme, sep, rest = address.strip().rpartition("://")
    if sep and scheme != "tcp":
        raise ValueError(f"only tcp:// addresses are supported, not {scheme}://")
    host, colon, port = rest.rpartition(":")
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError("not an address of the form tcp://HOST:PORT")
    return host, int(port)


def _connect(host: str, port: int, deadline: float) -> socket.socket:
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise ProbeError("the connection was not accepted")
        try:
            return socket.create_connection((host, port), timeout=left)
        except socket.timeout:
            raise ProbeError("the connection timed out") from None
        except ConnectionRefusedError:
            time.sleep(min(_RETRY_S, max(0.0, deadline - time.monotonic())))
        except OSError as e:  # a name that does not resolve, an unreachable network
            raise ProbeError(e.strerror or type(e).__name__) from None


def _send(sock: socket.socket, message: dict) -> None:
    import msgpack

    frame = msgpack.packb(message, use_bin_type=True)
    prelude = _Q.pack(1) + _Q.pack(len(frame))
    try:
        sock.sendall(_Q.pack(len(prelude) + len(frame)) + prelude + frame)
    except OSError as e:
        raise ProbeError(f"the connection failed ({e.strerror or type(e).__name__})") from None


def _receive(sock: socket.socket, deadline: float) -> Any:
    """One message's first frame, decoded as plain msgpack; the other frames are skipped unread."""
    import msgpack

    (total,) = _Q.unpack(_read(sock, _Q.size, deadline))
    if total > MAX_REPLY_BYTES or total < 2 * _Q.size:
        raise NotDask(f"it announced a message of {total} bytes, not Dask's framing")
    body = _read(sock, total, deadline)
    (nframes,) = _Q.unpack_from(body)
    if not 1 <= nframes <= MAX_FRAMES or (1 + nframes) * _Q.size > total:
        raise NotDask(f"it announced {nframes} frames, not Dask's framing")
    (first,) = _Q.unpack_from(body, _Q.size)
    start = (1 + nframes) * _Q.size
    if start + first > total:
        raise NotDask("its first frame is longer than its message")
    try:
        # no object_hook / ext_hook: ExtType stays an inert value, a {"__Pickled__": n} map a map;
        # arrays as tuples, as Dask reads them: a reply may use one as a map key
        return msgpack.unpackb(body[start:start + first], raw=False, strict_map_key=False, use_list=False)
    except Exception as e:  # msgpack's errors (malformed, too deep, trailing data) have no common base
        raise NotDask(f"its reply is not Dask's (msgpack: {type(e).__name__})") from None


def _read(sock: socket.socket, n: int, deadline: float) -> bytes:
    chunks, got = [], 0
    while got < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise ProbeTimeout("no answer")
        sock.settimeout(left)
        try:
            chunk = sock.recv(min(n - got, 2**20))
        except socket.timeout:
            raise ProbeTimeout("no answer") from None
        except OSError as e:
            raise ProbeError(f"the connection failed ({e.strerror or type(e).__name__})") from None
        if not chunk:
            raise ProbeError("the connection was closed")
        chunks.append(chunk)
        got += len(chunk)
    return b"".join(chunks)
