"""prsa_ctrl.studies.daskprobe, prsa-tune --scheduler and run_monte_carlo(scheduler="tcp://...")
against loopback servers that are not Dask schedulers (issue 31: a silent listener hung the run
for > 300 s, an HTTP server gave "needs more memory than this machine has", a port that closes at
once gave "numerical failure (CommClosedError)"). Every check runs under a short configured
deadline (0.5 s): the code under test bounds each test's time, never the test itself."""

import http.server
import re
import socket
import struct
import threading

import pytest

from prsa_ctrl.studies import daskprobe
from prsa_ctrl.studies.daskprobe import SchedulerProbeError, probe_scheduler

SHORT = 0.5  # s, the deadline the tests configure


class _Server:
    """A loopback TCP server on an ephemeral port whose accepted connections get ``handle``."""

    def __init__(self, handle):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.handle, self.conns, self.stop = handle, [], threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        self.sock.settimeout(0.05)
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except OSError:
                continue
            self.conns.append(conn)
            try:
                self.handle(conn)
            except OSError:
                pass

    def close(self):
        self.stop.set()
        self.thread.join(5)
        for c in self.conns:
            c.close()
        self.sock.close()


def _dask_handshake() -> bytes:
    """A genuine Dask handshake frame (what a scheduler sends first), built with Dask itself."""
    from distributed.protocol.core import dumps
    from distributed.protocol.utils import pack_frames

    info = {"compression": None, "python": (3, 11, 0), "pickle-protocol": 5}  # (Comm.handshake_info's keys)
    body = pack_frames(dumps(info))
    return struct.pack("<Q", len(body)) + body


HANDLERS = {
    # accepts, says nothing (a listener that never speaks)
    "silent": lambda conn: None,
    # closes every connection at once
    "closing": lambda conn: conn.close(),
    # talks first, in HTTP (an HTTP reply where Dask expects a frame length)
    "banner": lambda conn: conn.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n"),
    # a Dask handshake, then silence (the identity request is never answered)
    "handshake-only": lambda conn: conn.sendall(_dask_handshake()),
    # a plausible length, then too few bytes and a close
    "truncated": lambda conn: (conn.sendall(struct.pack("<Q", 100) + b"xy"), conn.close()),
}
EXPECT = {
    "silent": r"no answer \(a Dask handshake not received in time\)",
    "closing": r"the connection was closed before a Dask handshake",
    "banner": r"not a Dask scheduler \(its first bytes 'HTTP/1.1' are not a Dask handshake: a frame length of "
              r"\d+ bytes\)",
    "handshake-only": r"no answer \(no reply to Dask's identity request in time\)",
    "truncated": r"the connection was closed before the rest of the Dask handshake \(2 of 100 bytes\)",
}


@pytest.fixture(params=sorted(HANDLERS))
def server(request):
    if request.param == "handshake-only":
        pytest.importorskip("distributed")
    s = _Server(HANDLERS[request.param])
    s.kind = request.param
    yield s
    s.close()


@pytest.fixture
def http_server():
    """A real HTTP server (it answers only after a request: to Dask's probe it is silent)."""
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    t = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    t.start()
    yield srv.server_address[1]
    srv.shutdown()
    srv.server_close()


def test_probe_names_what_answered(server):
    with pytest.raises(SchedulerProbeError, match=EXPECT[server.kind]):
        probe_scheduler("127.0.0.1", server.port, SHORT)


def test_probe_of_an_http_server_is_no_answer(http_server):
    with pytest.raises(SchedulerProbeError, match=r"no answer \(a Dask handshake not received in time\)"):
        probe_scheduler("127.0.0.1", http_server, SHORT)


def test_probe_of_a_closed_port_cannot_connect():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(SchedulerProbeError, match=r"cannot connect \("):
        probe_scheduler("127.0.0.1", port, SHORT)


@pytest.mark.parametrize("kw, match", [({"timeout_s": 0}, "timeout_s = 0"), ({"timeout_s": float("nan")}, "timeout_s"),
                                       ({"timeout_s": True}, "timeout_s"), ({"port": 0}, "port = 0"),
                                       ({"port": 70000}, "port = 70000")])
def test_probe_arguments_are_checked(kw, match):
    args = {"host": "127.0.0.1", "port": 8786, "timeout_s": 1.0} | kw
    with pytest.raises(ValueError, match=match):
        probe_scheduler(**args)


def test_probe_accepts_a_real_scheduler_and_refuses_its_worker():
    distributed = pytest.importorskip("distributed", reason="Dask is an optional extra")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                                  host="127.0.0.1", dashboard_address=None,
                                  scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}) as cluster:
        host, port = cluster.scheduler_address[len("tcp://"):].rsplit(":", 1)
        probe_scheduler(host, int(port), 5.0)  # a generous deadline: a real answer takes ~10 ms
        worker = next(iter(cluster.workers.values())).address
        whost, wport = worker[len("tcp://"):].rsplit(":", 1)
        with pytest.raises(SchedulerProbeError, match=r"not a Dask scheduler \(a Dask Worker answered"):
            probe_scheduler(whost, int(wport), 5.0)


# --- the command and the API ---------------------------------------------------------------------

@pytest.fixture
def short_timeouts(monkeypatch):
    import prsa_ctrl.cli.tune as tune_cli

    monkeypatch.setattr(tune_cli, "SCHEDULER_CONNECT_TIMEOUT_S", SHORT)
    monkeypatch.setattr(daskprobe, "SCHEDULER_TIMEOUT_S", SHORT)


def test_prsa_tune_refuses_before_tuning(server, short_timeouts, stand_in, capsys):
    from prsa_ctrl.cli.tune import main

    address = f"tcp://127.0.0.1:{server.port}"
    rc = main(["--scene", "robust-load-step", "--monte-carlo", "2", "--scheduler", address])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, (rc, err)
    assert not stand_in, (rc, err)
    assert len(err) == 1, err
    assert "Traceback" not in err[0], err
    assert err[0].startswith(f"prsa-tune: error: --scheduler {address!r}: not a Dask scheduler / no answer at "
                             f"127.0.0.1:{server.port} within 0.5 s: "), err[0]
    assert re.search(EXPECT[server.kind], err[0]), err[0]


def test_prsa_tune_refuses_an_http_server_before_tuning(http_server, short_timeouts, stand_in, capsys):
    from prsa_ctrl.cli.tune import main

    address = f"tcp://127.0.0.1:{http_server}"
    rc = main(["--scene", "robust-load-step", "--monte-carlo", "2", "--scheduler", address])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2, (rc, err)
    assert not stand_in, (rc, err)
    assert len(err) == 1, (rc, err)
    assert f"--scheduler {address!r}: not a Dask scheduler / no answer" in err[0]
    assert "no answer (a Dask" in err[0]


def test_run_monte_carlo_refuses_before_any_work(server, short_timeouts, monkeypatch, paper_plant):
    from prsa_ctrl import PID
    from prsa_ctrl.studies import montecarlo as mc
    from prsa_ctrl.studies.scene import load_scene

    def no_work(*a, **k):
        raise AssertionError("reached the verification settings")

    monkeypatch.setattr(mc, "verification_settings", no_work)
    address = f"tcp://127.0.0.1:{server.port}"
    with pytest.raises(ValueError, match=rf"scheduler = {address!r}: not a Dask scheduler / no answer within 0.5 s: "
                                         + EXPECT[server.kind]):
        mc.run_monte_carlo(paper_plant, load_scene("robust-load-step"), {"a": PID(0.085, 14.7)}, 4, scheduler=address)


def test_probe_of_a_name_that_does_not_resolve(monkeypatch):
    def gaierror(*a, **k):  # (no resolver is asked: its answer time depends on the machine)
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", gaierror)
    with pytest.raises(SchedulerProbeError, match=r"cannot connect \(the host name does not resolve: Name or "
                                                  r"service not known\)"):
        probe_scheduler("no-such-host.invalid", 8786, SHORT)


def test_probe_bounds_a_resolver_that_does_not_answer(monkeypatch):
    """getaddrinfo has no timeout: a resolver that hangs is left behind at the deadline."""
    release = threading.Event()
    monkeypatch.setattr(socket, "getaddrinfo", lambda *a, **k: release.wait(60) and [])
    try:
        with pytest.raises(SchedulerProbeError, match=r"no answer \(the host name did not resolve in time\)"):
            probe_scheduler("scheduler.example", 8786, SHORT)
        # the probe's own deadline ended it: the resolver is still blocked, left behind
        assert any(t.name == "prsa-scheduler-resolve" and t.is_alive() for t in threading.enumerate())
    finally:
        release.set()
