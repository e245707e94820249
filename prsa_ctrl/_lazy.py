"""The one mechanism by which prsa-ctrl defers imports.

``import prsa_ctrl`` and loading a plant file must stay cheap (python-control alone takes about
2 s to import), so a package's public names are resolved on first use: each ``__init__.py``
lists ``name -> module`` and hands the table to :func:`lazy_exports`. Heavy third-party
libraries that a module needs only on some paths (python-control, matplotlib, filterpy, Dask)
are taken through :func:`module`, which imports on first attribute access.
"""

from __future__ import annotations

from importlib import import_module
from types import ModuleType
from typing import Any, Callable

__all__ = ["lazy_exports", "module"]


def lazy_exports(package: str, table: dict[str, str], eager: dict[str, Any] | None = None
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
    """Module-level ``__getattr__``, ``__dir__`` and ``__all__`` for a package.

    Parameters
    ----------
    package : str
        The package's ``__name__``.
    table : dict
        Public name -> module path relative to the package (e.g. ``"tune_pid": "tuning.generic"``);
        a path with a leading dot goes one level up (``".errors"`` in a subpackage is
        :mod:`prsa_ctrl.errors`).
    eager : dict, optional
        Names the package has already imported (cheap ones), listed in ``__all__`` as well.

    Returns
    -------
    (__getattr__, __dir__, __all__)
    """
    names = sorted({*table, *(eager or {})})

    def __getattr__(name: str) -> Any:
        if name in table:
            value = getattr(import_module(f".{table[name]}", package), name)
            import_module(package).__dict__[name] = value
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return list(names)

    return __getattr__, __dir__, names


class _Deferred(ModuleType):
    """A module object that imports the real module on first attribute access."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.__dict__["_target"] = None

    def _load(self) -> ModuleType:
        target = self.__dict__["_target"]
        if target is None:
            target = import_module(self.__name__)
            self.__dict__["_target"] = target
        return target

    def __getattr__(self, attr: str) -> Any:
        return getattr(self._load(), attr)

    def __dir__(self) -> list[str]:
        return dir(self._load())


def module(name: str) -> ModuleType:
    """A stand-in for ``import name`` that imports ``name`` on first attribute access.

    Examples
    --------
    >>> ct = module("control")   # nothing imported yet
    >>> callable(ct.tf)          # imported here
    True
    """
    return _Deferred(name)
