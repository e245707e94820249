"""``prsa-app``: serve the tuning app on the loopback interface.

Exit codes: 0 after Ctrl-C, SIGTERM or a normal stop (every page closed, the uploaded files
removed, one line ``prsa-app: stopped (Ctrl-C|SIGTERM)``), 2 for bad input (flags, plant or
scene files, a port in use, the ``app`` extra missing), one line ``prsa-app: error: ...`` and
no traceback.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from ..textsafe import MESSAGE_CHARS_MAX, printable

__all__ = ["main", "build_parser", "serve", "free_port"]

PROG = "prsa-app"
#: The interpreter's thread switch interval while serving, s (Python's default: 0.005).
SWITCH_INTERVAL_S = 0.0005


class _Usage(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2 (argparse prints the usage too)
        raise _Usage(message)


def _port(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--port {text!r}: expected an integer port in [0, 65535] (0: a free one)") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"--port {text}: expected an integer port in [0, 65535] (0: a free one)")
    return v


#: Flags whose value may start with ``-``: glued to it, so that the value is refused by name.
_VALUE_FLAGS = ("--plant", "--scene", "--port")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog=PROG, description="Interactive speed-loop tuning in the browser (serves on 127.0.0.1).")
    p.add_argument("--plant", help="built-in plant name or plant .toml file (default paper-iprsm)")
    p.add_argument("--scene", help="built-in load-step scene name or scene .toml file (default paper-load-step)")
    p.add_argument("--port", type=_port, default=0, help="port on 127.0.0.1 (default 0: a free port, printed)")
    p.add_argument("--no-browser", action="store_true", help="do not open a browser")
    return p


def serve(plant: str | None = None, scene: str | None = None, port: int = 0):
    """Start (not run) the Bokeh server on 127.0.0.1; returns it (``server.port`` is the port).

    Raises
    ------
    AppInputError
        A bad plant or scene (one line).
    OSError
        The port cannot be bound.
    """
    from bokeh.server.server import Server

    from . import application
    from .gate import CHECK_UNUSED_S, UNUSED_SESSION_S

    app = application(plant, scene, warm=True)
    attempts = 20 if port == 0 else 1  # a free port can be taken between the probe and the bind
    for i in range(attempts):
        p = port or free_port()
        try:
            _probe(p)  # tornado leaks its socket when the bind fails
            server = Server({"/": app}, address="127.0.0.1", port=p, num_procs=1,
                            allow_websocket_origin=[f"127.0.0.1:{p}", f"localhost:{p}"],
                            unused_session_lifetime_milliseconds=UNUSED_SESSION_S * 1000,
                            check_unused_sessions_milliseconds=CHECK_UNUSED_S * 1000)
            server.prsa_gate = app.prsa_gate  # the pages, closed when the app stops (main)
            return server
        except OSError:
            if i == attempts - 1:
                raise
    raise AssertionError("unreachable")


def _probe(port: int) -> None:
    """Raise OSError if ``port`` cannot be bound on 127.0.0.1 (as the server binds it)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))


def free_port() -> int:
    """A TCP port the OS reports free on 127.0.0.1 (free when asked; another process may take it).

    Returns
    -------
    int
    """
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``prsa-app``; returns the exit code."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if "-h" in argv or "--help" in argv:
        build_parser().print_help()
        return 0
    from ..cli.common import UsageError, attach_values, long_options

    parser = build_parser()
    try:  # a value that starts with '-' (--port -x) reaches its flag's check (:func:`prsa_ctrl.cli.common.attach_values`)
        argv = attach_values(argv, _VALUE_FLAGS, long_options(parser))
        args = parser.parse_args(argv)
    except (_Usage, UsageError) as exc:
        print(printable(f"{PROG}: error: {' '.join(str(exc).split())}"), file=sys.stderr)
        return 2
    try:
        import bokeh  # noqa: F401
    except ImportError:
        print(f"{PROG}: error: the app needs its optional dependencies; expected them installed: "
              "pip install \"prsa-ctrl[app]\"", file=sys.stderr)
        return 2
    from .session import AppInputError

    try:
        server = serve(args.plant, args.scene, args.port)
    except AppInputError as exc:
        print(printable(f"{PROG}: error: {exc}", limit=MESSAGE_CHARS_MAX), file=sys.stderr)  # a file's text, escaped
        return 2
    except OSError as exc:
        print(f"{PROG}: error: --port {args.port}: cannot listen on 127.0.0.1 ({exc.strerror or exc}); expected a free "
              "port (0 picks one)", file=sys.stderr)
        return 2
    url = f"http://127.0.0.1:{server.port}/"
    # the event loop shares the GIL with the threads that build pages and tune: it gets the
    # GIL back within SWITCH_INTERVAL_S of asking (Python's default 5 ms made every socket
    # operation wait behind a build, and a flood of page loads 40 times slower)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    print(f"{PROG}: serving {url} (Ctrl-C to stop)", flush=True)
    import signal

    stopped_by = []

    def on_term(signum, frame):  # SIGTERM stops the app as Ctrl-C does
        stopped_by.append("SIGTERM")
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        server.start()
        if not args.no_browser:
            import webbrowser

            server.io_loop.add_callback(webbrowser.open, url)
        server.io_loop.start()
    except KeyboardInterrupt:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # the clean-up is not interrupted
        _stop(server)
        print(f"{PROG}: stopped ({stopped_by[0] if stopped_by else 'Ctrl-C'})", file=sys.stderr)
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _stop(server) -> None:
    """Stop serving and close every page: workers stopped, a running ``prsa-fit`` ended, the
    uploaded files removed (the server's temporary folders)."""
    try:
        server.stop()
    except Exception:  # noqa: BLE001 - a half-started server: the pages are closed all the same
        pass
    gate = getattr(server, "prsa_gate", None)
    if gate is not None:
        gate.shutdown()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
