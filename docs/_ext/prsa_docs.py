"""Sphinx directives of the prsa-ctrl documentation, generated from the code at build time.

- ``prsa-api MODULE`` (reStructuredText pages, or ``{eval-rst}`` blocks in MyST): the API reference of one (sub)package, made from its ``__all__``: a summary
  table, then every public name documented by autodoc (numpydoc docstrings). Nothing is listed
  by hand, so the reference follows the code when modules inside a subpackage are split or moved.
- ``prsa-api-toplevel``: the names of ``prsa_ctrl.__all__``, each linked to the subpackage page
  that documents it (a name that no subpackage exports is documented on the top-level page).
- ``prsa-plant-keys``: every key of a plant file (``prsa_ctrl.plant.SCHEMA``) with its unit, kind,
  plausible range and reason (``PLAUSIBLE``), and the value and source in the built-in
  ``paper-iprsm`` plant.

No file is written: the generated reStructuredText is parsed in memory.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re
import tomllib
import warnings

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective

logger = logging.getLogger(__name__)

#: Modules of the package that are not subpackages but carry public names of their own.
PLAIN_MODULES = ("prsa_ctrl.errors", "prsa_ctrl.options")

# Key suffix -> unit, longest first (plant files put the unit in the key's name).
_UNITS = (
    ("_n_m_s_per_rad", "N m s/rad"),
    ("_n_per_mm_e", "N/mm^e"),
    ("_n_s_per_mm", "N s/mm"),
    ("_counts_per_rev", "counts/rev"),
    ("_kg_m2", "kg m^2"),
    ("_m_s", "m/s"),
    ("_n_m", "N m"),
    ("_deg", "deg"),
    ("_hz", "Hz"),
    ("_kg", "kg"),
    ("_mm", "mm"),
    ("_um", "um"),
    ("_n", "N"),
    ("_s", "s"),
)


def documented_modules() -> list[str]:
    """Every module the API reference documents: each subpackage of prsa_ctrl, plus PLAIN_MODULES."""
    import prsa_ctrl

    subs = [f"prsa_ctrl.{m.name}" for m in pkgutil.iter_modules(prsa_ctrl.__path__) if m.ispkg]
    # Data packages (built-in plants, scenes, templates) hold files, not API.
    subs = [s for s in subs if getattr(importlib.import_module(s), "__all__", None)]
    return sorted(subs) + [m for m in PLAIN_MODULES if _has(m)]


def _has(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


def public_names(module: str) -> list[tuple[str, str]]:
    """``(name, where)`` for every public name of ``module``; ``where`` is relative to ``module``.

    ``where`` is the name itself, except where a submodule of the same name shadows it (after
    the submodule is imported, ``module.name`` is that submodule): then the object is documented
    where it is defined, ``submodule.name``. Submodules listed in ``__all__`` are skipped.
    """
    mod = importlib.import_module(module)
    out = []
    for n in mod.__all__:
        obj = getattr(mod, n)
        if not inspect.ismodule(obj):
            out.append((n, n))
        elif hasattr(obj, n) and not inspect.ismodule(getattr(obj, n)):
            out.append((n, f"{obj.__name__[len(module) + 1:]}.{n}"))
    return out


def _object(full: str):
    parent, name = full.rsplit(".", 1)
    return getattr(importlib.import_module(parent), name)


def _is_data(obj) -> bool:
    return not (inspect.isclass(obj) or callable(obj))


def _attr_docs(module: str) -> dict:
    from sphinx.pycode import ModuleAnalyzer

    try:
        return ModuleAnalyzer.for_module(module).find_attr_docs()
    except Exception:  # no source: nothing to find
        return {}


def _data_doc(package: str, name: str, obj) -> list[str]:
    """The ``#:`` comment that documents a constant where it is assigned (a submodule of the
    package: autodoc, which reads the comments of the module it is given, does not find it)."""
    pkg = importlib.import_module(package)
    subs = [package] + [m.name for m in pkgutil.walk_packages(getattr(pkg, "__path__", []), prefix=f"{package}.")]
    if ("", name) in _attr_docs(package):
        return []
    for sub in subs:
        try:
            mod = importlib.import_module(sub)
        except ImportError:  # an optional dependency of that module is missing: it defines no constant here
            continue
        if vars(mod).get(name) is obj and sub != package:  # in ``package`` itself autodoc finds it
            docs = _attr_docs(sub)
            if ("", name) in docs:
                lines = [line for line in docs[("", name)] if line.strip()]
                escape_bars(None, "data", name, obj, {}, lines)
                return lines
    return []


def _auto(module: str, where: str) -> list[str]:
    full = f"{module}.{where}"
    obj = _object(full)
    if inspect.isclass(obj) and issubclass(obj, BaseException):
        return [f".. autoexception:: {full}", "   :members:", ""]
    if inspect.isclass(obj):
        return [f".. autoclass:: {full}", "   :members:", ""]
    if callable(obj):
        return [f".. autofunction:: {full}", ""]
    value = repr(obj)
    lines = [f".. autodata:: {full}"]
    lines += ["   :no-value:"] if len(value) > 70 else []
    lines.append("")
    doc = _data_doc(module, where.rsplit(".", 1)[-1], obj)
    lines += [f"   {line}" for line in doc] or [f"   ``{type(obj).__name__}``"]
    return lines + [""]


class ApiDirective(SphinxDirective):
    required_arguments = 1

    def run(self):
        module = self.arguments[0]
        names = public_names(module)
        api = [w for _, w in names if not _is_data(_object(f"{module}.{w}"))]
        data = [w for _, w in names if _is_data(_object(f"{module}.{w}"))]
        lines = [f".. automodule:: {module}", "   :no-members:", ""]
        if api:
            lines += [".. autosummary::", "   :nosignatures:", "", *[f"   {w}" for w in api], ""]
        for where in api:
            lines += _auto(module, where)
        if data:
            lines += [".. rubric:: Constants", ""]
            for where in data:
                lines += _auto(module, where)
        return self._parse(lines)

    def _parse(self, lines):
        node = nodes.section()
        node.document = self.state.document
        self.state.nested_parse(StringList(lines, source=f"<prsa-api {self.arguments[0] if self.arguments else ''}>"),
                                self.content_offset, node, match_titles=True)
        return node.children


class TopLevelDirective(ApiDirective):
    required_arguments = 0

    def run(self):
        import prsa_ctrl

        where = {}
        for module in documented_modules():
            mod = importlib.import_module(module)
            for n, at in public_names(module):
                obj = importlib.import_module(f"{module}.{at}".rsplit(".", 1)[0])
                where.setdefault((n, id(getattr(obj, n))), f"{module}.{at}")
        rows, alone = [], []
        for n in prsa_ctrl.__all__:
            target = where.get((n, id(getattr(prsa_ctrl, n))))
            if target is None:  # exported at the top only: documented on this page
                alone.append(n)
                target = f"prsa_ctrl.{n}"
            rows += [f"   * - ``prsa_ctrl.{n}``", f"     - :py:obj:`{target}`"]
        lines = [".. list-table::", "   :header-rows: 1", "", "   * - name", "     - documented as", *rows, ""]
        if alone:
            lines += ["Exported by ``prsa_ctrl`` but by none of its subpackages:", ""]
            for n in alone:
                lines += _auto("prsa_ctrl", n)
        return self._parse(lines)


def _rst_text(text: str) -> str:
    """Plain text as reStructuredText (no markup character of the text takes effect)."""
    return re.sub(r"([\\*`_|])", r"\\\1", str(text))


def _unit(key: str) -> str:
    return next((u for suffix, u in _UNITS if key.endswith(suffix)), "-")


def _defaulted_entry(key: str) -> dict:
    """The paper plant's value and source of a key its file leaves out (the documented default)."""
    import warnings

    from prsa_ctrl.plant import load_plant

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plant = load_plant("paper-iprsm")
    return {"value": plant.values[key], "source": plant.sources[key]}


class PlantKeysDirective(ApiDirective):
    required_arguments = 0

    def run(self):
        from prsa_ctrl.plant import PLAUSIBLE, SCHEMA, plant_file_path

        with open(plant_file_path("paper-iprsm"), "rb") as f:
            paper = tomllib.load(f)
        lines = [".. list-table::", "   :header-rows: 1", "   :class: prsa-keys", "",
                 "   * - key", "     - unit", "     - kind", "     - accepted (plausible range: why)",
                 "     - paper-iprsm: value, source"]
        for section, keys in SCHEMA.items():
            for key, kind in keys.items():
                full = f"{section}.{key}"
                lo, hi, why = PLAUSIBLE[full]
                entry = paper[section].get(key) or _defaulted_entry(full)  # a key the file leaves out
                lines += [f"   * - ``{full}``", f"     - {_unit(key)}", f"     - {kind}",
                          f"     - [{lo:g}, {hi:g}]: {_rst_text(why)}",
                          f"     - ``{entry['value']}``: {_rst_text(entry['source'])}"]
        lines.append("")
        return self._parse(lines)


# A literal span (``x``), a role (:math:`x`) or an already escaped bar: left as they are.
_KEEP = re.compile(r"(``.+?``|:[\w:+-]+:`[^`]*`|\\\|)")
_TABLE_OR_LINE_BLOCK = re.compile(r"^\s*(\| |\+[-=+])")


def escape_bars(app, what, name, obj, options, lines):
    """Show ``|x|`` in docstrings as the magnitude bars they are, not as rst substitutions.

    The docstrings write magnitudes and norms as ``|S|`` or ``|e|``; reStructuredText would read
    them as substitution references (an error). Bars inside literal spans and roles, and lines
    that are rst tables or line blocks (starting with ``| `` or ``+-``/``+=``), are left alone.
    """
    for i, line in enumerate(lines):
        if "|" not in line or _TABLE_OR_LINE_BLOCK.match(line):
            continue
        parts = _KEEP.split(line)
        lines[i] = "".join(p if k % 2 else p.replace("|", "\\|") for k, p in enumerate(parts))


def _numpydoc_warnings_to_sphinx() -> None:
    """numpydoc reports a docstring it cannot parse (an unknown section, whose text it drops) as a
    Python ``UserWarning``, which ``sphinx-build -W`` would not count: report it as a Sphinx warning."""
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if "numpydoc" in str(filename):
            logger.warning("numpydoc: %s", message, type="prsa", subtype="numpydoc")
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show


def _numpydoc_template_once() -> None:
    """Compile numpydoc's docstring template once per builder instead of once per object.

    numpydoc (1.x) builds a new Jinja environment and compiles its ``numpydoc_docstring.rst``
    template at every ``get_doc_object`` call, twice per function (its signature and its
    docstring): about 2,600 compilations, 15 % of this site's build. The template depends on the
    builder alone, so it is compiled once per builder and the rendering is unchanged. Where
    numpydoc's internals differ from the ones this relies on, numpydoc is left as it is.
    """
    try:
        from numpydoc import docscrape_sphinx as ds
        from numpydoc import numpydoc as nd

        for name in ("BuiltinTemplateLoader", "FileSystemLoader", "SandboxedEnvironment", "get_doc_object_orig",
                     "SphinxClassDoc", "SphinxFunctionDoc", "SphinxObjDoc"):
            getattr(ds, name)
        expected = ["obj", "what", "doc", "config", "builder"]
        if list(inspect.signature(nd.get_doc_object).parameters) != expected or nd.get_doc_object is not ds.get_doc_object:
            return
    except (ImportError, AttributeError):
        return
    import os

    templates: dict = {}  # id(builder) -> (builder, template); the builder is kept so its id stays its own

    def template(builder):
        if id(builder) not in templates:
            dirs = [os.path.join(os.path.dirname(ds.__file__), "templates")]
            if builder is not None:
                loader = ds.BuiltinTemplateLoader()
                loader.init(builder, dirs=dirs)
            else:
                loader = ds.FileSystemLoader(dirs)
            templates[id(builder)] = builder, ds.SandboxedEnvironment(loader=loader).get_template("numpydoc_docstring.rst")
        return templates[id(builder)][1]

    def get_doc_object(obj, what=None, doc=None, config=None, builder=None):
        config = {} if config is None else config
        config["template"] = template(builder)
        return ds.get_doc_object_orig(obj, what=what, doc=doc, config=config, class_doc=ds.SphinxClassDoc,
                                      func_doc=ds.SphinxFunctionDoc, obj_doc=ds.SphinxObjDoc)

    nd.get_doc_object = get_doc_object


def setup(app):
    _numpydoc_warnings_to_sphinx()
    _numpydoc_template_once()
    # Before numpydoc (priority 500) turns the sections into rst.
    app.connect("autodoc-process-docstring", escape_bars, priority=400)
    app.add_directive("prsa-api", ApiDirective)
    app.add_directive("prsa-api-toplevel", TopLevelDirective)
    app.add_directive("prsa-plant-keys", PlantKeysDirective)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
