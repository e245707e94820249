"""The one output writer of the command-line tools (``--json``, ``--plots``, ``--out``,
``--export``, ``prsa-fit --out``).

Rules, in order of checking:

* An empty path, a path whose directory does not exist, or a directory that cannot be written
  is refused (:class:`OutputError`, a ``ValueError``) -- :func:`check_writable` does this
  *before* the expensive work, so that a run never ends with a result it cannot save.
* A symlink is written *through*: the file it points to is replaced, the link stays a link.
* An existing target that is not a regular file (directory, device node, FIFO, socket) is
  refused.
* The target may not be any input file of the run (plant, scene, data files): compared by
  resolved path and by inode (``os.path.samefile``), so hard links and ``..`` do not get round it.
* The content goes to a temporary file in the target's own directory, named
  ``.NAME.prsa-tmp-XXXXXXXX`` so that a leftover after ``SIGKILL`` is recognisable; it is
  removed on every exit path Python sees (exceptions, ``KeyboardInterrupt``), and renamed onto
  the target atomically (``os.replace``): readers see the old or the new file, never a part.
* An existing file keeps its permission bits; a new file gets ``0o666`` minus the umask, like
  any file the user's shell would create.

A replaced file is a new inode: other hard links to the old file keep the old content.
"""

from __future__ import annotations

import math
import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

__all__ = ["OutputError", "TEMP_MARK", "json_safe", "check_writable", "check_distinct", "check_directory", "write_text",
           "write_file",
           "make_directory", "remove_created", "live_temporaries", "cleanup_temporaries"]

#: Marker in the name of every temporary file: ``.NAME.prsa-tmp-XXXXXXXX``.
TEMP_MARK = ".prsa-tmp-"

_LIVE: set[str] = set()


class OutputError(ValueError):
    """An output path cannot (or must not) be written; the message names it as typed."""


def _umask() -> int:
    try:  # Linux: read without changing it (os.umask is process-wide and not thread safe)
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _label(path: str | os.PathLike, flag: str) -> str:
    return f"{flag} {str(path)!r}" if flag else repr(str(path))


def _probe(directory: str, what: str) -> None:
    """Create and remove a temporary file in ``directory`` (the only true writability test:
    permissions, read-only and pseudo file systems, quotas on the directory entry)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".probe{TEMP_MARK}", dir=directory)
    except OSError as exc:
        raise OutputError(f"{what}: cannot create a file in directory {directory!r} ({exc.strerror or exc})") from None
    os.close(fd)
    os.unlink(tmp)


def _same(a: str, b: str) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_writable(path: str | os.PathLike, inputs: Iterable[str | os.PathLike] = (), flag: str = "") -> Path:
    """Check that a file can be written at ``path`` under the rules of this module.

    Parameters
    ----------
    path : str or path-like
        The output file as the user typed it.
    inputs : iterable of path-like
        Every input file of the run; none of them may be the output.
    flag : str
        The option that named the path (``"--json"``), used in messages.

    Returns
    -------
    Path
        The file that will really be replaced (the symlink target for a symlink).

    Raises
    ------
    OutputError
        One line naming the path as typed and the reason.

    Examples
    --------
    >>> check_writable("", flag="--json")
    Traceback (most recent call last):
    ...
    prsa_ctrl.output.OutputError: --json '': expected a file path
    """
    what = _label(path, flag)
    text = os.fspath(path)
    if not str(text).strip():
        raise OutputError(f"{what}: expected a file path")
    if str(text).endswith(os.sep):
        raise OutputError(f"{what}: names a directory; expected a file path")
    target = os.path.realpath(text)  # follows symlinks (a dangling one: its would-be target)
    if os.path.lexists(target):
        st = os.stat(target)
        if stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{what}: is a directory; expected a file path")
        if not stat.S_ISREG(st.st_mode):
            raise OutputError(f"{what}: exists and is not a regular file (device, FIFO or socket); refusing to replace it")
    for inp in inputs:
        if inp is not None and os.path.exists(inp) and os.path.exists(target) and _same(target, os.fspath(inp)):
            raise OutputError(f"{what}: is an input file of this run ({os.fspath(inp)}); refusing to overwrite it")
        if inp is not None and os.path.realpath(os.fspath(inp)) == target:
            raise OutputError(f"{what}: is an input file of this run ({os.fspath(inp)}); refusing to overwrite it")
    parent = os.path.dirname(target) or "."
    if not os.path.isdir(parent):
        raise OutputError(f"{what}: directory {os.path.dirname(text) or '.'!r} does not exist")
    _probe(parent, what)
    return Path(target)


def check_distinct(paths: "dict[str, str | os.PathLike | None]") -> None:
    """Refuse two outputs of one run that name the same file (the second write would replace
    the first): compared by resolved path and, for existing files, by inode.

    Parameters
    ----------
    paths : dict
        ``{flag: path as typed}``; ``None`` paths are skipped.

    Raises
    ------
    OutputError
        ``--out 'a.toml' and --json 'a.toml' name the same path; expected different files``.

    Examples
    --------
    >>> check_distinct({"--out": "a.toml", "--json": "./a.toml"})
    Traceback (most recent call last):
    ...
    prsa_ctrl.output.OutputError: --out 'a.toml' and --json './a.toml' name the same path; expected different files
    """
    items = [(f, os.fspath(p)) for f, p in paths.items() if p is not None]
    for i, (fa, pa) in enumerate(items):
        for fb, pb in items[i + 1:]:
            same = os.path.realpath(pa) == os.path.realpath(pb) or (
                os.path.exists(pa) and os.path.exists(pb) and _same(pa, pb))
            if same:
                raise OutputError(f"{fa} {pa!r} and {fb} {pb!r} name the same path; expected different files")


def _existing_ancestor(path: str) -> str:
    p = os.path.abspath(path)
    while not os.path.lexists(p):
        p = os.path.dirname(p)
    return p


def check_directory(path: str | os.PathLike, flag: str = "") -> Path:
    """Check that ``path`` is, or can be created as, a writable directory (nothing is created).

    Raises
    ------
    OutputError
        For an empty path, a path under a regular file, or an unwritable location.
    """
    what = _label(path, flag)
    text = os.fspath(path)
    if not str(text).strip():
        raise OutputError(f"{what}: expected a directory path")
    if os.path.lexists(text):
        if not os.path.isdir(text):
            raise OutputError(f"{what}: exists and is not a directory")
        _probe(os.path.realpath(text), what)
        return Path(os.path.realpath(text))
    anc = _existing_ancestor(text)
    if not os.path.isdir(anc):
        raise OutputError(f"{what}: {anc!r} is not a directory, so nothing can be created under it")
    _probe(os.path.realpath(anc), what)
    return Path(os.path.abspath(text))


def make_directory(path: str | os.PathLike, flag: str = "") -> list[Path]:
    """Create ``path`` (and missing parents); return the directories that were created, deepest
    last, for :func:`remove_created` to take back on failure."""
    check_directory(path, flag)
    created: list[Path] = []
    p = Path(os.path.abspath(os.fspath(path)))
    missing = []
    while not p.exists():
        missing.append(p)
        p = p.parent
    for d in reversed(missing):
        try:
            d.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            remove_created(created)
            raise OutputError(f"{_label(path, flag)}: cannot create {str(d)!r} ({exc.strerror or exc})") from None
        created.append(d)
    return created


def remove_created(created: Iterable[Path]) -> None:
    """Remove directories made by :func:`make_directory` if they are still empty."""
    for d in reversed(list(created)):
        try:
            d.rmdir()
        except OSError:
            pass


def write_file(path: str | os.PathLike, producer: Callable[[Path], None],
               inputs: Iterable[str | os.PathLike] = (), flag: str = "") -> Path:
    """Write a file under the rules of this module.

    Parameters
    ----------
    path : str or path-like
        The output file (a symlink is written through to its target).
    producer : callable
        ``producer(tmp)`` writes the complete content into the temporary file ``tmp`` (a
        :class:`~pathlib.Path` in the target's directory whose suffix is not the target's:
        pass an explicit format, e.g. ``fig.savefig(tmp, format="png")``).
    inputs : iterable of path-like
        The run's input files, which are never overwritten.
    flag : str
        The option that named the path, for messages.

    Returns
    -------
    Path
        The file written (the symlink target for a symlink).
    """
    target = check_writable(path, inputs, flag)
    mode = stat.S_IMODE(os.stat(target).st_mode) if target.exists() else 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}{TEMP_MARK}", dir=target.parent)
    _LIVE.add(tmp)
    try:
        os.close(fd)
        producer(Path(tmp))
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    finally:
        try:
            if os.path.lexists(tmp):
                os.unlink(tmp)
        finally:
            _LIVE.discard(tmp)
    return target


def write_text(path: str | os.PathLike, text: str, inputs: Iterable[str | os.PathLike] = (), flag: str = "") -> Path:
    """Write UTF-8 ``text`` to ``path`` with :func:`write_file`.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_text(d / "a.txt", "hello\\n")
    >>> (d / "a.txt").read_text(), [p.name for p in d.iterdir()]
    ('hello\\n', ['a.txt'])
    """
    return write_file(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), inputs, flag)


def live_temporaries() -> list[str]:
    """Temporary files being written right now (for an emergency exit)."""
    return sorted(_LIVE)


def cleanup_temporaries() -> None:
    """Remove every temporary file still being written (used before a forced exit)."""
    for tmp in list(_LIVE):
        try:
            os.unlink(tmp)
        except OSError:
            pass
        _LIVE.discard(tmp)


def json_safe(obj: Any) -> Any:
    """``obj`` with non-finite floats (unfinished runs, targets never reached, infinite
    margins) as ``None`` and numpy scalars as Python numbers, ready for strict JSON.

    Examples
    --------
    >>> json_safe({"a": float("inf"), "b": [1.0, float("nan")], "c": "x"})
    {'a': None, 'b': [1.0, None], 'c': 'x'}
    """
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if type(obj).__module__ == "numpy" and hasattr(obj, "item") and getattr(obj, "ndim", 1) == 0:
        return json_safe(obj.item())
    return obj

