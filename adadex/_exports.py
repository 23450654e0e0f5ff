"""Lazy re-exports for the subpackages' ``__init__`` (PEP 562).

Each subpackage names its public classes and functions once, grouped by the module that defines
them; ``from adadex.modules import Tracker`` then imports :mod:`adadex.modules.tracker` on first use
only, so ``import adadex.modules`` (and the ``adadex`` command) does not pay for torch, TorchRL or
MuJoCo until a name that needs them is asked for.

A few exported functions share their name with the module that defines them (``adadex.eval.evaluate``,
``adadex.transforms.modulation``, ...). The package attribute is always the function
(``from adadex.eval import evaluate`` gives the function, whether or not the module was imported
before); the module itself is ``importlib.import_module("adadex.eval.evaluate")``.
"""

from __future__ import annotations

import importlib
import types
from collections.abc import Callable, Mapping, Sequence


def lazy_exports(package: str, exports: Mapping[str, Sequence[str]]
                 ) -> tuple[list[str], Callable[[str], object], Callable[[], list[str]]]:
    """The ``__all__``, ``__getattr__`` and ``__dir__`` of ``package`` re-exporting ``exports``.

    Args:
        package: the package's ``__name__``.
        exports: defining module (absolute name) → the public names it defines, in the order
            ``__all__`` lists them.

    Returns:
        ``(__all__, __getattr__, __dir__)``, to assign at the package's top level.
    """
    where = {name: module for module, names in exports.items() for name in names}
    if len(where) != sum(len(names) for names in exports.values()):
        raise ValueError(f"{package}: a name is exported twice")
    all_names = list(where)
    module_object = importlib.import_module(package)
    namespace = module_object.__dict__
    # an exported name that is also a submodule's name: importing the submodule must not replace it
    shadowed = {name for name, module in where.items() if module.rpartition(".")[2] == name}
    if shadowed:
        module_object.__class__ = _shadowing_package(frozenset(shadowed))
        for name in shadowed:
            if isinstance(namespace.get(name), types.ModuleType):
                del namespace[name]

    def __getattr__(name: str):
        module = where.get(name)
        if module is None:      # AttributeError lets ``from package import submodule`` fall back to the import
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value                         # once imported, a plain attribute
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(all_names))

    return all_names, __getattr__, __dir__


def _shadowing_package(shadowed: frozenset[str]) -> type:
    class Package(types.ModuleType):
        """A package whose exported functions keep their names when their same-named submodule is
        imported (the import system sets the submodule as the package's attribute; that is skipped)."""

        def __setattr__(self, name, value):
            if name in shadowed and isinstance(value, types.ModuleType):
                return
            super().__setattr__(name, value)

    return Package
