"""Package attributes imported on first access (PEP 562).

A package whose ``__init__`` re-exports its modules' names would import them all with the
package; programs that need one module (the VSD worker process, ``bopsurg eval`` before it
starts that worker) would pay for every other. A package instead declares where each name
lives and calls, at its end::

    lazy_exports(__name__, {"load_json": ".jsonio", ...})
"""

from __future__ import annotations

import importlib
import sys
import types
from collections.abc import Mapping
from typing import Any


def lazy_exports(package: str, homes: Mapping[str, str]) -> None:
    """Make each name of ``homes`` an attribute of ``package`` that is imported from its
    module (relative to ``package``) when first asked for.

    A name that is also the name of its own module (``bopsurg.metrics.vsd``, the function,
    lives in ``bopsurg.metrics.vsd``, the module) stays the exported object once that module
    is imported, as with an eager ``from .vsd import vsd`` in ``__init__``.
    """
    module = sys.modules[package]
    shadowed = {n for n, home in homes.items() if home == f".{n}"}

    class _LazyPackage(types.ModuleType):
        def __getattr__(self, name: str) -> Any:
            home = homes.get(name)
            if home is None:
                raise AttributeError(f"module {package!r} has no attribute {name!r}")
            value = getattr(importlib.import_module(home, package), name)
            types.ModuleType.__setattr__(self, name, value)
            return value

        def __setattr__(self, name: str, value: Any) -> None:
            if name in shadowed and isinstance(value, types.ModuleType):
                return  # the import system binding the submodule: keep the export
            types.ModuleType.__setattr__(self, name, value)

        def __dir__(self) -> list[str]:
            return sorted({*vars(self), *homes})

    module.__class__ = _LazyPackage
