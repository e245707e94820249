"""The one output writer of the command-line tools (``--json``, ``--plots``, ``--out``,
``--export``, ``prsa-fit --out``).

Rules, in order of checking:

* ``-`` (the Unix spelling of standard output) is refused rather than written as a file named
  ``-``; ``./-`` names such a file.
* An empty path, a path whose directory does not exist, or a directory that cannot be written
  is refused (:class:`OutputError`, a ``ValueError``) -- :func:`check_writable` does this
  *before* the expensive work, so that a run never ends with a result it cannot save. So are a
  file name longer than the file system takes (``NAME_MAX``, 255 bytes on Linux), a path longer
  than ``PATH_MAX``, a symlink loop, and a path under a file.
* Nothing is written into the package's own data (its modules, the built-in plants and
  scenes): :func:`package_roots`.
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
* Several outputs of one run are written all or nothing with :class:`Transaction`: every
  file is complete in its temporary first, then all are renamed in one go (a rename within a
  directory does not fail once the temporary exists there).

A replaced file is a new inode: other hard links to the old file keep the old content.
"""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterable

from ..errors import OutputError
from ..results import json_safe  # defined with the result objects; re-exported here

__all__ = ["OutputError", "TEMP_MARK", "json_safe", "check_writable", "check_distinct", "check_directory", "write_text",
           "write_file", "Transaction", "package_roots",
           "make_directory", "remove_created", "live_temporaries", "cleanup_temporaries"]

#: Marker in the name of every temporary file: ``.NAME.prsa-tmp-XXXXXXXX``.
TEMP_MARK = ".prsa-tmp-"

_LIVE: set[str] = set()


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
    try:
        os.close(fd)
    finally:  # removed after a Ctrl-C too
        os.unlink(tmp)


def package_roots() -> list[str]:
    """Resolved folders of the package's own files: its modules and the built-in plants and
    scenes (installed package data, or the repository's ``plants/`` and ``tuning/`` in an
    editable install). No output is written inside them."""
    from ..plant.plantfile import builtin_root

    roots = [os.path.dirname(os.path.dirname(os.path.realpath(__file__)))]  # prsa_ctrl/io/output.py -> prsa_ctrl
    for pkg, folder in (("prsa_ctrl.plants", "plants"), ("prsa_ctrl.scenes", "tuning")):
        try:
            roots.append(os.path.realpath(os.fspath(builtin_root(pkg, folder))))
        except TypeError:  # a resource container that is not a folder (zip): nothing to write into
            pass
    return roots


def _check_not_package(target: str, what: str) -> None:
    for root in package_roots():
        if target == root or target.startswith(root.rstrip(os.sep) + os.sep):
            raise OutputError(f"{what}: is inside the prsa-ctrl package's own files ({root}); refusing to write there "
                              "(the built-in plants and scenes would be replaced); expected a path outside it")


def _name_max(directory: str) -> int:
    try:
        return os.pathconf(directory, "PC_NAME_MAX")
    except (OSError, ValueError):
        return 255


def _path_max(directory: str) -> int:
    try:
        return os.pathconf(directory, "PC_PATH_MAX")
    except (OSError, ValueError):
        return 4096


def _check_lengths(text: str, parent: str, what: str) -> None:
    """Refuse a component longer than ``NAME_MAX`` or a path longer than ``PATH_MAX`` (bytes)."""
    nmax = _name_max(parent if os.path.isdir(parent) else ".")
    for part in Path(text).parts:
        n = len(os.fsencode(part))
        if n > nmax:
            raise OutputError(f"{what}: the name {part[:24]!r}... is {n} bytes long; expected at most {nmax} bytes "
                              "per file or folder name")
    n = len(os.fsencode(os.path.abspath(text)))
    pmax = _path_max(parent if os.path.isdir(parent) else ".")
    if n >= pmax:
        raise OutputError(f"{what}: the path is {n} bytes long; expected fewer than {pmax} bytes")


def _stat_or_none(text: str, what: str) -> os.stat_result | None:
    """``os.stat`` (through symlinks), ``None`` for a path that does not exist yet; a symlink
    loop, a path under a file or an unreachable folder is an :class:`OutputError`."""
    import errno

    try:
        return os.stat(text)
    except FileNotFoundError:
        return None
    except OSError as exc:
        why = {errno.ELOOP: "is a symlink loop (or a chain of more than 40 links)",
               errno.ENOTDIR: "is under a file, which is not a directory",
               errno.ENAMETOOLONG: "is too long for the file system",
               errno.EACCES: "cannot be reached (permission denied on a folder)"}.get(
                   exc.errno, f"cannot be examined ({exc.strerror or exc})")
        raise OutputError(f"{what}: {why}; expected a path to a writable file or folder") from None


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
    prsa_ctrl.errors.OutputError: --json '': expected a file path
    """
    what = _label(path, flag)
    text = os.fspath(path)
    if not str(text).strip():
        raise OutputError(f"{what}: expected a file path")
    if str(text).endswith(os.sep):
        raise OutputError(f"{what}: names a directory; expected a file path")
    if str(text) == "-":  # the Unix spelling of standard output: a file named '-' is a surprise
        raise OutputError(f"{what}: standard output is not an output of these tools; expected a file path "
                          "(write ./- for a file named '-')")
    _check_lengths(text, os.path.dirname(os.path.abspath(text)), what)
    st = _stat_or_none(text, what)
    target = os.path.realpath(text)  # follows symlinks (a dangling one: its would-be target)
    _check_lengths(target, os.path.dirname(target), what)
    _check_not_package(target, what)
    if st is not None:
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
    prsa_ctrl.errors.OutputError: --out 'a.toml' and --json './a.toml' name the same path; expected different files
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
    _check_lengths(text, _existing_ancestor(text), what)
    st = _stat_or_none(text, what)
    _check_not_package(os.path.realpath(text), what)
    if st is not None or os.path.lexists(text):
        if st is None or not stat.S_ISDIR(st.st_mode):
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
    with Transaction(inputs) as tr:
        target = tr.stage(path, producer, flag)
        tr.commit()
    return target


class Transaction:
    """Several output files written all or nothing.

    :meth:`stage` checks a path (:func:`check_writable`) and writes its complete content into
    a temporary file beside the target; :meth:`commit` renames every staged file onto its
    target; leaving the ``with`` block without :meth:`commit` (an error, Ctrl-C) removes every
    temporary and every directory made by :meth:`make_directory`, so no target changes.

    Parameters
    ----------
    inputs : iterable of path-like
        The run's input files, which are never overwritten.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with Transaction() as tr:
    ...     _ = tr.stage(d / "a.txt", lambda tmp: tmp.write_text("a"))
    ...     _ = tr.stage(d / "b.txt", lambda tmp: tmp.write_text("b"))
    ...     sorted(p.name for p in d.iterdir() if not p.name.startswith("."))
    ...     tr.commit()
    []
    >>> sorted(p.name for p in d.iterdir())
    ['a.txt', 'b.txt']
    """

    def __init__(self, inputs: Iterable[str | os.PathLike] = ()) -> None:
        self.inputs = [i for i in inputs if i is not None]
        self._staged: list[tuple[str, Path]] = []
        self.created: list[Path] = []
        self.committed = False
        #: The outputs as typed (files and folders), in place after :meth:`commit`.
        self.written: list[str] = []
        self._listed: list[str] = []

    def __enter__(self) -> "Transaction":
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self.committed:
            self.abort()

    def make_directory(self, path: str | os.PathLike, flag: str = "") -> None:
        """Create a directory for outputs (taken back by :meth:`abort` while still empty)."""
        self.created.extend(make_directory(path, flag))
        self._listed.append(os.fspath(path))

    def stage(self, path: str | os.PathLike, producer: Callable[[Path], None], flag: str = "",
              listed: bool = True) -> Path:
        """Check ``path`` and write its complete content (``producer(tmp)``) into a temporary
        beside it; returns the file that :meth:`commit` will replace. ``listed``: name it in
        :attr:`written` (files of a folder made by :meth:`make_directory` are not)."""
        target = check_writable(path, self.inputs, flag)
        if listed:
            self._listed.append(os.fspath(path))
        mode = stat.S_IMODE(os.stat(target).st_mode) if target.exists() else 0o666 & ~_umask()
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name[:64]}{TEMP_MARK}", dir=target.parent)
        _LIVE.add(tmp)
        self._staged.append((tmp, target))
        os.close(fd)
        producer(Path(tmp))
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)
        return target

    def commit(self) -> None:
        """Rename every staged file onto its target (the only step after all are complete)."""
        for tmp, target in self._staged:
            os.replace(tmp, target)
            _LIVE.discard(tmp)
        self._staged.clear()
        self.committed = True
        self.written = list(self._listed)

    def abort(self) -> None:
        """Remove every temporary and the directories this transaction created (nothing
        after :meth:`commit`)."""
        if self.committed:
            return
        for tmp, _ in self._staged:
            try:
                if os.path.lexists(tmp):
                    os.unlink(tmp)
            except OSError:
                pass
            _LIVE.discard(tmp)
        self._staged.clear()
        remove_created(self.created)
        self.created.clear()


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
