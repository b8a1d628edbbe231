"""Build dfusion's API reference from its docstrings with pdoc (``make docs``).

Usage::

    python docs/build_api.py OUT_DIR

writes one HTML page per module of the ``dfusion`` package (every module, not only
those a package lists in ``__all__``), an index and a search index to ``OUT_DIR``.
Docstrings are read as numpy style (pdoc's ``numpy`` format also converts the
reStructuredText roles such as ``:class:`...```); formulas in ``:math:`` roles are
rendered with MathJax.

Warnings are errors: pdoc's own (a module that cannot be imported, an annotation
that cannot be parsed, ...) and this script's, which pdoc does not give: every
cross-reference in a docstring (``:class:`X```, ``:func:`X```, ``:meth:``, ``:mod:``,
``:attr:``, ``:exc:``, ``:data:``, ``:obj:``) and every ``dfusion.``-qualified name
quoted in backticks must name something that exists. A name is looked up as an
absolute import path, then in the namespace of the module (and class) whose
docstring holds it, then in that module's parent packages. The build exits with
status 1 and lists every unresolved reference.

See docs/api-reference.md for why pdoc.
"""
from __future__ import annotations

import argparse
import builtins
import dataclasses
import html
import importlib
import inspect
import pkgutil
import re
import sys
import typing
import warnings
from collections.abc import Iterator
from pathlib import Path

import pdoc
import pdoc.doc
import pdoc.render

PACKAGE = "dfusion"

#: Sphinx roles whose target must resolve.
_ROLE = re.compile(r"(?::py)?:(mod|func|data|const|class|meth|attr|exc|obj):`([^`]+)`")
#: ``dfusion.``-qualified names quoted in single or double backticks.
_QUALIFIED = re.compile(r"(?<![:\w])``?(~?dfusion(?:\.\w+)+)(?:\(\))?``?")

_MISSING = object()


def module_names(package: str = PACKAGE) -> list[str]:
    """Every importable module of ``package``, packages first, without private ones."""
    pkg = importlib.import_module(package)
    names = [package] + [m.name for m in pkgutil.walk_packages(pkg.__path__, f"{package}.")]
    return sorted(n for n in names if not any(part.startswith("_") for part in n.split(".")))


def materialize_lazy_exports(names: list[str]) -> None:
    """Bind the names a package exports lazily (a module ``__getattr__``, as
    :mod:`dfusion.run` does so that a node process does not import the launcher) into
    the module, in this process only: pdoc reads ``module.__dict__`` and would
    otherwise report every such name in ``__all__`` as unresolvable."""
    for name in names:
        mod = importlib.import_module(name)
        if "__getattr__" not in mod.__dict__:
            continue
        for export in getattr(mod, "__all__", []):
            if export not in mod.__dict__:
                mod.__dict__[export] = getattr(mod, export)


def resolve_namedtuple_annotations(names: list[str]) -> None:
    """Give every ``NamedTuple`` of these modules evaluated field annotations, in this
    process only. Under ``from __future__ import annotations`` the generated
    ``__new__`` holds them as strings, and pdoc evaluates those in the namespace
    ``collections.namedtuple`` created, where module names such as ``Array`` do not
    exist; :func:`typing.get_type_hints` evaluates them in the class's module."""
    for name in names:
        mod = importlib.import_module(name)
        for obj in list(vars(mod).values()):
            if inspect.isclass(obj) and obj.__module__ == name and issubclass(obj, tuple) \
                    and hasattr(obj, "_fields") and getattr(obj, "__annotations__", None):
                hints = typing.get_type_hints(obj)
                obj.__new__.__annotations__ = {k: hints[k] for k in obj._fields if k in hints}


def _getattr_chain(obj: object, parts: list[str]) -> object:
    for part in parts:
        nxt = getattr(obj, part, _MISSING)
        if nxt is _MISSING:
            nxt = _field(obj, part)
        if nxt is _MISSING:
            return _MISSING
        obj = nxt
    return obj


def _field(obj: object, name: str) -> object:
    """A dataclass field, an annotated attribute or an attribute a method sets (``self.name = ...``)."""
    if not inspect.isclass(obj):
        return _MISSING
    for klass in obj.__mro__:
        if dataclasses.is_dataclass(klass) and name in {f.name for f in dataclasses.fields(klass)}:
            return name
        if name in getattr(klass, "__annotations__", {}):
            return name
        try:
            src = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        if re.search(rf"\bself\.{re.escape(name)}\s*(?::[^=]*)?=", src):
            return name
    return _MISSING


def _import_path(name: str) -> object:
    if not name or name.startswith(".") or not all(p.isidentifier() for p in name.split(".")):
        return _MISSING
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            mod = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        return _getattr_chain(mod, parts[i:])
    return _MISSING


def resolve(name: str, module: str, cls: type | None = None) -> bool:
    """Whether reference ``name`` found in a docstring of ``module`` (class ``cls``) names something."""
    name = name.strip().lstrip("~!").removesuffix("()")
    if "<" in name:  # "text <target>" form
        name = name.rsplit("<", 1)[1].rstrip(">")
    if name.startswith("."):  # relative to the package (of a module docstring's module)
        base = module if hasattr(importlib.import_module(module), "__path__") else module.rpartition(".")[0]
        while name.startswith(".."):
            name, base = name[1:], base.rpartition(".")[0]
        name = base + name
    parts = name.split(".")
    if _import_path(name) is not _MISSING:
        return True
    scopes: list[object] = []
    if cls is not None:
        scopes.append(cls)
    mod = importlib.import_module(module)
    scopes.append(mod)
    scopes.append(builtins)
    pkg = module
    while "." in pkg:
        pkg = pkg.rpartition(".")[0]
        scopes.append(importlib.import_module(pkg))
    if any(_getattr_chain(scope, parts) is not _MISSING for scope in scopes):
        return True
    # a name quoted as a string value of the module (an entry-point group, a logger name)
    return any(isinstance(v, str) and v == name for v in vars(mod).values())


def _docs(module: pdoc.doc.Module) -> Iterator[tuple[pdoc.doc.Doc, type | None]]:
    """The module's own documented objects (not re-exports, not inherited members)."""
    yield module, None
    stack: list[pdoc.doc.Namespace] = [module]
    while stack:
        ns = stack.pop()
        for member in ns.own_members:
            if member.taken_from[0] != module.modulename or getattr(member, "is_inherited", False):
                continue
            cls = member.obj if isinstance(member, pdoc.doc.Class) else (
                ns.obj if isinstance(ns, pdoc.doc.Class) else None)
            yield member, cls
            if isinstance(member, pdoc.doc.Class):
                stack.append(member)


def unresolved_references(modules: dict[str, pdoc.doc.Module]) -> list[str]:
    """``"module.qualname: :role:`target`"`` for every reference that names nothing."""
    bad = []
    for modname, module in modules.items():
        for doc, cls in _docs(module):
            text = doc.docstring or ""
            refs = [(f":{role}:", target) for role, target in _ROLE.findall(text)]
            refs += [("``", target) for target in _QUALIFIED.findall(text)]
            for role, target in refs:
                if not resolve(target, modname, cls):
                    bad.append(f"{doc.fullname}: {role}`{target}`")
    return sorted(set(bad))


#: ``dfusion.``-qualified names in Markdown code spans.
_MD_QUALIFIED = re.compile(r"`(dfusion(?:\.\w+)+)(?:\(\))?[`(\[]")


def _string_constants(package: str = PACKAGE) -> set[str]:
    """String values defined at module level anywhere in the package (entry-point groups, ...)."""
    out: set[str] = set()
    for name in module_names(package):
        out |= {v for v in vars(importlib.import_module(name)).values() if isinstance(v, str)}
    return out


def unresolved_names_in_markdown(paths: list[Path]) -> list[str]:
    """``"file:line: name"`` for every ``dfusion.``-qualified name in a Markdown code span
    that is neither an importable module nor an attribute of one (nor a string
    constant of the package, such as the plug-in entry-point group)."""
    constants = _string_constants()
    bad = []
    for path in paths:
        for lineno, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
            for name in _MD_QUALIFIED.findall(line):
                if name not in constants and _import_path(name) is _MISSING:
                    bad.append(f"{path}:{lineno}: {name}")
    return bad


#: Repository paths in Markdown code spans: ``dfusion/x.py``, ``tests/t.py::test_name``, ``docs/a.md#part``.
_MD_PATH = re.compile(r"`((?:dfusion|tests|examples|benchmarks|docs|topologies|nodes)/[\w./-]+?"
                      r"\.(?:py|md|toml|gz|log|npz|json))(?:::(\w+))?(?:#[\w-]+)?`")


def missing_paths_in_markdown(paths: list[Path], root: Path) -> list[str]:
    """``"file:line: path"`` for every repository file quoted in a Markdown code span that
    does not exist (or whose ``::name`` is not defined in it). Placeholders such as
    ``topologies/x.toml`` are the caller's to leave out."""
    bad = []
    for path in paths:
        for lineno, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
            for rel, name in _MD_PATH.findall(line):
                target = Path(root) / rel
                if not target.is_file():
                    bad.append(f"{path}:{lineno}: {rel}")
                elif name and not re.search(rf"^\s*(?:async\s+)?(?:def|class)\s+{name}\b",
                                            target.read_text(encoding="utf-8"), re.MULTILINE):
                    bad.append(f"{path}:{lineno}: {rel}::{name}")
    return bad


def _summary(module: pdoc.doc.Module) -> str:
    """The first sentence of a module's docstring, as plain text."""
    text = " ".join((module.docstring or "").strip().split("\n\n")[0].split())
    return re.sub(r":\w+:`~?([^`]+)`", r"\1", text).replace("``", "").split(". ")[0].rstrip(".")


def index_html(modules: dict[str, pdoc.doc.Module]) -> str:
    """The index page: every package with its first sentence, its modules below it.
    (pdoc's own index follows the top package's ``__all__`` and listed 2 of its packages.)"""
    packages = sorted(n for n, m in modules.items() if m.is_package)
    rows = []
    for pkg in packages:
        subs = sorted(n for n in modules if n.rpartition(".")[0] == pkg and not modules[n].is_package)
        link = f'<a href="{pkg.replace(".", "/")}.html"><code>{html.escape(pkg)}</code></a>'
        mods = ", ".join(f'<a href="{n.replace(".", "/")}.html"><code>{html.escape(n.rpartition(".")[2])}</code></a>'
                         for n in subs)
        rows.append(f"<dt>{link}</dt><dd>{html.escape(_summary(modules[pkg]))}"
                    + (f"<br><small>modules: {mods}</small>" if mods else "") + "</dd>")
    top = [n for n in modules if "." in n and not modules[n].is_package and n.count(".") == 1]
    rows += [f'<dt><a href="{n.replace(".", "/")}.html"><code>{html.escape(n)}</code></a></dt>'
             f"<dd>{html.escape(_summary(modules[n]))}</dd>" for n in sorted(top)]
    return ("<!doctype html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>dfusion API reference</title>"
            "<style>body{font-family:sans-serif;max-width:60em;margin:2em auto;line-height:1.4}dd{margin:0 0 .8em 1.5em}"
            "</style></head><body><h1>dfusion API reference</h1>"
            f"<p>{len(packages)} packages and {len(modules)} modules; every page has a search box "
            "(start at <a href=\"dfusion.html\"><code>dfusion</code></a>).</p><dl>"
            + "".join(rows) + "</dl></body></html>\n")


def build(out_dir: Path) -> list[Path]:
    """Render every module of dfusion into ``out_dir``; raise on any warning or bad reference."""
    pdoc.render.configure(docformat="numpy", math=True, search=True, show_source=False)   # source view: 3x slower
    out_dir = Path(out_dir)
    written = []
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        names = module_names()
        materialize_lazy_exports(names)
        resolve_namedtuple_annotations(names)
        modules = {name: pdoc.doc.Module.from_name(name) for name in names}
        bad = unresolved_references(modules)
        if bad:
            raise RuntimeError(f"{len(bad)} unresolved cross-reference(s) in docstrings:\n  " + "\n  ".join(bad))
        for module in modules.values():
            html = pdoc.render.html_module(module, modules)
            path = out_dir / f"{module.fullname.replace('.', '/')}.html"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(html, encoding="utf-8")
            written.append(path)
        (out_dir / "index.html").write_text(index_html(modules), encoding="utf-8")
        (out_dir / "search.js").write_text(pdoc.render.search_index(modules), encoding="utf-8")
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path, help="where the HTML goes (created if missing)")
    args = ap.parse_args(argv)
    try:
        pages = build(args.out_dir)
    except (RuntimeError, Warning) as e:
        print(f"make docs: FAILED: {e}", file=sys.stderr)
        return 1
    print(f"API reference: {len(pages)} module pages in {args.out_dir}/ (open {args.out_dir}/index.html)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
