"""Lazy package exports (PEP 562), shared by the ``estimation``, ``perception`` and
``mapping`` packages so that importing a package costs nothing until a name is used."""
from __future__ import annotations

import importlib
import sys
from collections.abc import Callable


def lazy_exports(package: str, modules: dict[str, tuple[str, ...]]
                 ) -> tuple[list[str], Callable[[str], object], Callable[[], list[str]]]:
    """Return ``__all__``, ``__getattr__`` and ``__dir__`` for ``package``.

    ``modules`` maps each absolute module name to the public names it defines; the first
    access to a name imports its module and caches the value in the package namespace.
    """
    exports = {name: module for module, names in modules.items() for name in names}

    def __getattr__(name: str):  # noqa: N807
        module_name = exports.get(name)
        if module_name is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module_name), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:  # noqa: N807
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return sorted(exports), __getattr__, __dir__
