"""Is there a Dask scheduler at ``tcp://HOST:PORT``? A bounded check before any work.

Dask's own client waits without a limit for the first message of whatever answers at the
address (``distributed.comm.connect`` reads the peer's handshake with no timeout): a listener that
never speaks hung ``prsa-tune --scheduler`` for more than 300 s; an HTTP server's reply was read as
a 3 EiB frame length ("needs more memory than this machine has"); a port that closes at once
ended the run after the tuning with "CommClosedError" (issue 31). :func:`probe_scheduler` asks
first, within one deadline:

1. a TCP connection (the host name resolved on a thread of its own: ``getaddrinfo`` has no
   timeout);
2. the peer's handshake, read on the raw socket: a Dask listener sends it as soon as it accepts
   (``distributed.comm.core.Listener.on_connection`` writes before it reads): an 8-byte frame
   length, at most :data:`MAX_HANDSHAKE_BYTES`, then frames that decode to Dask's handshake
   (a mapping with ``python`` and ``pickle-protocol``);
3. Dask's ``identity`` request over a Dask connection (``distributed.comm.connect``, the
   whole exchange under ``asyncio.wait_for``): the reply's ``type`` must be ``Scheduler`` (a
   worker or nanny also speaks Dask).

Nothing is allocated from a number the peer sends before it is bounded, and every read waits at
most until the deadline.
"""

from __future__ import annotations

import math
import queue
import socket
import struct
import threading
import time

from ..errors import SchedulerProbeError

__all__ = ["SCHEDULER_TIMEOUT_S", "MAX_HANDSHAKE_BYTES", "SchedulerProbeError", "probe_scheduler"]

#: Seconds the whole check may take (connection, handshake and identity), by default.
SCHEDULER_TIMEOUT_S = 5.0
#: Largest first message accepted as a Dask handshake (bytes; a real one is ~100).
MAX_HANDSHAKE_BYTES = 1 << 16


def _recv_exactly(sock: socket.socket, n: int, deadline: float, what: str) -> bytes:
    """``n`` bytes from ``sock`` before ``deadline`` (``time.monotonic``), else
    :class:`SchedulerProbeError` saying what was awaited."""
    buf = bytearray()
    while len(buf) < n:
        left = deadline - time.monotonic()
        if left <= 0:
            raise SchedulerProbeError(f"no answer ({what} not received in time)")
        sock.settimeout(left)
        try:
            chunk = sock.recv(min(n - len(buf), 1 << 16))
        except socket.timeout:
            raise SchedulerProbeError(f"no answer ({what} not received in time)") from None
        except OSError as exc:
            raise SchedulerProbeError(f"the connection failed while waiting for {what} "
                                      f"({exc.strerror or type(exc).__name__})") from None
        if not chunk:
            raise SchedulerProbeError(f"the connection was closed before {what}"
                                      + (f" ({len(buf)} of {n} bytes)" if buf else ""))
        buf += chunk
    return bytes(buf)


def _resolve(host: str, port: int, deadline: float) -> list:
    """``socket.getaddrinfo`` bounded by the deadline (it has no timeout of its own: it runs on a
    daemon thread that is left behind if the resolver does not answer in time)."""
    out: queue.Queue = queue.Queue(1)

    def work() -> None:
        try:
            out.put((True, socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)))
        except (OSError, UnicodeError) as exc:
            out.put((False, exc))

    threading.Thread(target=work, daemon=True, name="prsa-scheduler-resolve").start()
    try:
        ok, val = out.get(timeout=max(deadline - time.monotonic(), 1e-3))
    except queue.Empty:
        raise SchedulerProbeError("no answer (the host name did not resolve in time)") from None
    if not ok:
        raise SchedulerProbeError(f"cannot connect (the host name does not resolve: "
                                  f"{getattr(val, 'strerror', None) or type(val).__name__})")
    return val


def _connect(host: str, port: int, deadline: float) -> socket.socket:
    """Step 1: a TCP connection to the first address of ``host`` that accepts one."""
    why = "no address"
    for family, kind, proto, _, addr in _resolve(host, port, deadline):
        left = deadline - time.monotonic()
        if left <= 0:
            raise SchedulerProbeError("no answer (the TCP connection was not accepted in time)")
        sock = socket.socket(family, kind, proto)
        sock.settimeout(left)
        try:
            sock.connect(addr)
            return sock
        except socket.timeout:
            sock.close()
            raise SchedulerProbeError("no answer (the TCP connection was not accepted in time)") from None
        except OSError as exc:
            sock.close()
            why = exc.strerror or type(exc).__name__
    raise SchedulerProbeError(f"cannot connect ({why})")


def _handshake(host: str, port: int, deadline: float) -> str:
    """Steps 1 and 2 of the module's check; returns the peer's IP address (step 3 connects to
    it, so that the host name is resolved once, within the deadline)."""
    sock = _connect(host, port, deadline)
    peer = sock.getpeername()[0]
    with sock:
        head = _recv_exactly(sock, 8, deadline, "a Dask handshake")
        (size,) = struct.unpack("<Q", head)
        if not 8 <= size <= MAX_HANDSHAKE_BYTES:
            shown = head.decode("ascii", "replace").encode("unicode_escape").decode("ascii")
            raise SchedulerProbeError(f"not a Dask scheduler (its first bytes {shown!r} are not a Dask "
                                      f"handshake: a frame length of {size} bytes)")
        body = _recv_exactly(sock, size, deadline, "the rest of the Dask handshake")
    try:
        from distributed.protocol.core import loads
        from distributed.protocol.utils import unpack_frames

        msg = loads(unpack_frames(body), deserialize=False)
    except Exception as exc:  # anything a garbled message raises while decoding
        raise SchedulerProbeError(f"not a Dask scheduler (its first message does not decode as a Dask "
                                  f"handshake: {type(exc).__name__})") from None
    if not isinstance(msg, dict) or "python" not in msg or "pickle-protocol" not in msg:
        raise SchedulerProbeError("not a Dask scheduler (its first message is not a Dask handshake)")
    return peer


async def _identity(address: str, left: float) -> object:
    from distributed.comm import connect

    comm = await connect(address, timeout=left)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        comm.abort()


def _scheduler_identity(address: str, deadline: float) -> None:
    """Step 3 of the module's check, on a thread of its own (its own event loop: the caller may
    be inside one, e.g. a notebook)."""
    import asyncio
    from concurrent.futures import ThreadPoolExecutor

    left = deadline - time.monotonic()
    if left <= 0:
        raise SchedulerProbeError("no answer (the identity request was not sent in time)")

    def ask():
        return asyncio.run(asyncio.wait_for(_identity(address, left), left))

    with ThreadPoolExecutor(1, thread_name_prefix="prsa-scheduler-probe") as pool:
        try:
            reply = pool.submit(ask).result()
        except (asyncio.TimeoutError, TimeoutError):
            raise SchedulerProbeError("no answer (no reply to Dask's identity request in time)") from None
        except MemoryError:
            raise SchedulerProbeError("not a Dask scheduler (its reply claims more memory than this machine "
                                      "has)") from None
        except Exception as exc:  # CommClosedError, OSError, a garbled reply
            raise SchedulerProbeError(f"not a Dask scheduler (the identity request failed: "
                                      f"{type(exc).__name__})") from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        raise SchedulerProbeError(f"not a Dask scheduler (a Dask {kind or 'peer'} answered; expected the "
                                  "scheduler's address, by default port 8786)")


def probe_scheduler(host: str, port: int, timeout_s: float = SCHEDULER_TIMEOUT_S) -> None:
    """Check that a Dask scheduler answers at ``tcp://host:port`` within ``timeout_s`` seconds in
    all (the three steps of the module's docstring).

    Parameters
    ----------
    host : str
        Host name or IP address (IPv6 without brackets).
    port : int
        TCP port 1..65535.
    timeout_s : float, s
        Deadline of the whole check (> 0, at most 600).

    Raises
    ------
    SchedulerProbeError
        One line: "cannot connect (...)", "no answer (...)" or "not a Dask scheduler (...)".
    ValueError
        ``timeout_s`` or ``port`` out of range.
    """
    if isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) or not (
            math.isfinite(timeout_s) and 0 < timeout_s <= 600):
        raise ValueError(f"timeout_s = {timeout_s!r}; expected a number of seconds in (0, 600]")
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ValueError(f"port = {port!r}; expected a TCP port 1..65535")
    deadline = time.monotonic() + float(timeout_s)
    ip = _handshake(host, port, deadline)
    _scheduler_identity(f"tcp://[{ip}]:{port}" if ":" in ip else f"tcp://{ip}:{port}", deadline)
