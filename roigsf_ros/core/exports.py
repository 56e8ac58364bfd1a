"""Lazy package exports: a layer's ``__init__`` names its public API without importing every module up front.

Importing one module of a layer (``roigsf_ros.data.bags`` for a node) must not pull in the heavy others
(open3d for ``data.scene``); PEP 562's module ``__getattr__`` imports a name's module on first use, and its module
``__dir__`` lists the exported names, so ``dir()``, tab completion and ``help()`` show the API before it is imported.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Sequence
from importlib import import_module
from typing import Any


def lazy_exports(
    package: str, modules: Mapping[str, Sequence[str]]
) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``(__all__, __getattr__, __dir__)`` for ``package``: a name in ``modules[mod]`` comes from ``package.mod`` when
    used; ``dir(package)`` lists those names with what the package already holds.
    """
    owner = {name: f"{package}.{mod}" for mod, names in modules.items() for name in names}
    if len(owner) != sum(len(names) for names in modules.values()):
        raise ValueError(f"{package}: a name is exported by two modules")

    def __getattr__(name: str) -> Any:  # noqa: N807 - the PEP 562 hook
        if name not in owner:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(import_module(owner[name]), name)

    def __dir__() -> list[str]:  # noqa: N807 - the PEP 562 hook
        return sorted(set(vars(sys.modules[package])) | set(owner))

    return sorted(owner), __getattr__, __dir__


__all__ = ["lazy_exports"]
