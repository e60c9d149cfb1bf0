"""Names of a package imported on first use (PEP 562), for packages whose modules are costly to import."""

from __future__ import annotations

import importlib


def lazy_names(package: str, where: dict[str, str], namespace: dict):
    """The module-level ``__getattr__`` and ``__dir__`` of ``package`` that import each name of ``where`` (name →
    module, absolute or relative to ``package``) when it is first asked for, and keep it in ``namespace`` (the package's
    ``globals()``) so that it is imported once.

    Examples
    --------
    In a package's ``__init__.py``::

        __getattr__, __dir__ = lazy_names(__name__, {"measure_stack": ".tiles"}, globals())
    """

    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where[name], package), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(list(namespace) + list(where))

    return __getattr__, __dir__
