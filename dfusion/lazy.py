"""Lazy package exports: a package names its public objects and imports each on first use.

Every package ``__init__`` of dfusion keeps ``_WHERE = {name: (module, attribute)}`` and
``__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)``, so that
``import dfusion.x`` loads nothing else (a node program imports only what its sensor kind
needs) while ``from dfusion.x import Name`` works as usual (PEP 562 module ``__getattr__``).
"""
from __future__ import annotations

import importlib
from typing import Any, Callable, Mapping, Sequence

__all__ = ["lazy_exports"]


def lazy_exports(package: str, where: Mapping[str, tuple[str, str | None]], namespace: dict[str, Any],
                 names: Sequence[str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package``.

    ``where[name] = (module, attribute)``: ``name`` is ``getattr(import_module(module),
    attribute)`` (the module itself when ``attribute`` is None), imported on first use and then
    kept in ``namespace`` (the package's ``globals()``); ``names`` is its ``__all__``.
    """

    def __getattr__(name: str) -> Any:
        """Import a public name on first use, so that importing the package loads nothing else."""
        found = where.get(name)
        if found is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        module, attribute = found
        obj = importlib.import_module(module)
        if attribute is not None:
            obj = getattr(obj, attribute)
        namespace[name] = obj
        return obj

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(names))

    return __getattr__, __dir__
