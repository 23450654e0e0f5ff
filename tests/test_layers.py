"""The package's layers, read from the source: every ``import`` (also those inside functions) of every
module under ``adadex/`` goes down the stack or sideways within a layer, never up, and no two modules
import each other, directly or around a cycle.

Layers, bottom to top (ARCHITECTURE.md): sim < data < envs < modules < transforms < eval < train;
``sysid`` stands beside the RL stack and uses only sim and data. The top-level helper modules
(``adadex.errors``, ``adadex.io``, ``adadex.arrays``, ``adadex.quat``, ...) sit below everything;
``adadex.cli`` sits on top.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "adadex"
STACK = ("sim", "data", "envs", "modules", "transforms", "eval", "train")
ALLOWED = {layer: set(STACK[: i + 1]) for i, layer in enumerate(STACK)}
ALLOWED["sysid"] = {"sim", "data", "sysid"}
TOP = "cli"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every adadex module ``path`` imports, at any depth of its syntax tree."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "adadex"}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] == "adadex":
                found.add(mod)
                # ``from adadex.x import y`` may name the submodule adadex.x.y
                found |= {f"{mod}.{a.name}" for a in node.names if _is_module(f"{mod}.{a.name}")}
    return found


def _is_module(name: str) -> bool:
    p = PACKAGE.parent.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _layer(module: str) -> str | None:
    """The layer of ``adadex.<layer>...``; None for the top-level helper modules."""
    parts = module.split(".")
    if len(parts) == 1:
        return None
    if parts[1] in STACK or parts[1] in ("sysid", TOP):
        return parts[1]
    return None


SOURCES = sorted(p for p in PACKAGE.rglob("*.py") if "assets" not in p.relative_to(PACKAGE).parts)
GRAPH = {_module_name(p): {m for m in _imports(p) if _is_module(m)} for p in SOURCES}


def test_the_layers_are_known():
    names = {p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert names <= set(STACK) | {"sysid"}, f"a package outside the declared layers: {names - set(STACK) - {'sysid'}}"


@pytest.mark.parametrize("module", sorted(GRAPH))
def test_imports_go_down(module):
    mine = _layer(module)
    bad = []
    for dep in sorted(GRAPH[module]):
        theirs = _layer(dep)
        if mine == TOP or theirs is None:
            continue                                   # the CLI may use anything; helpers are below all
        if mine is None or theirs == TOP or theirs not in ALLOWED[mine]:
            bad.append(dep)
    assert not bad, f"{module} (layer {mine}) imports upward or across: {bad}"


def test_no_import_cycles():
    """No module reaches itself through the import graph (package ``__init__`` re-exports excluded:
    a package importing its own submodules is how Python packages are made)."""
    def deps(m):
        return {d for d in GRAPH.get(m, ()) if not m.startswith(d + ".") and d != m}

    cycles, state = [], {}

    def visit(m, stack):
        state[m] = "open"
        stack.append(m)
        for d in sorted(deps(m)):
            if state.get(d) == "open":
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d, stack)
        stack.pop()
        state[m] = "done"

    for m in sorted(GRAPH):
        if m not in state:
            visit(m, [])
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_every_adadex_exception_derives_from_the_root():
    """One error root: every exception class defined under adadex/ subclasses adadex.AdadexError."""
    import importlib
    import inspect

    from adadex import AdadexError

    strays = []
    for name in sorted(GRAPH):
        if name.endswith("__main__"):
            continue
        module = importlib.import_module(name)
        for cls_name, cls in vars(module).items():
            if (inspect.isclass(cls) and issubclass(cls, BaseException) and cls.__module__ == name
                    and not issubclass(cls, AdadexError)):
                strays.append(f"{name}.{cls_name}")
    assert not strays, f"exception classes outside the adadex.AdadexError root: {strays}"
