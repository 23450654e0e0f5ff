"""The public API surface: every subpackage re-exports its public names (``from adadex.modules import
Tracker``), each name in ``__all__`` imports, the ``TYPE_CHECKING`` imports say the same as the lazy
table, and ``import adadex`` (or any subpackage) stays cheap: no torch, TorchRL or MuJoCo."""

from __future__ import annotations

import ast
import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "adadex"
SUBPACKAGES = ("sim", "data", "envs", "modules", "transforms", "eval", "train", "sysid")
HEAVY = ("torch", "torchrl", "tensordict", "mujoco")


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_every_public_name_imports(name):
    package = importlib.import_module(f"adadex.{name}")
    assert package.__all__, f"adadex.{name} exports nothing"
    assert len(set(package.__all__)) == len(package.__all__)
    for attr in package.__all__:
        value = getattr(package, attr)
        defined_in = package._EXPORTS and next(m for m, names in package._EXPORTS.items() if attr in names)
        assert value is getattr(importlib.import_module(defined_in), attr)
        if callable(value) and hasattr(value, "__module__"):
            assert value.__module__.startswith("adadex."), f"adadex.{name}.{attr} is not adadex's own"
        assert attr in dir(package)
    with pytest.raises(AttributeError):
        getattr(package, "no_such_name")


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_type_checking_imports_match_the_lazy_table(name):
    """The ``if TYPE_CHECKING:`` block (what type checkers and IDEs read) names the same names, from the
    same modules, as the table ``__getattr__`` serves."""
    tree = ast.parse((PACKAGE / name / "__init__.py").read_text(encoding="utf-8"))
    static: dict[str, list[str]] = {}
    for node in tree.body:
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                static.setdefault(imp.module, []).extend(a.name for a in imp.names)
    package = importlib.import_module(f"adadex.{name}")
    assert static == {m: list(n) for m, n in package._EXPORTS.items()}


def test_star_import():
    namespace: dict = {}
    exec("from adadex.modules import *", namespace)
    assert "Tracker" in namespace and "Modulator" in namespace


def test_submodules_still_import_through_the_package():
    from adadex.sim import objects                     # a submodule, not an exported name

    assert objects.__name__ == "adadex.sim.objects"


def _loaded_after(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json\n"
                          f"print(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"],
                         capture_output=True, text=True, check=True, timeout=120)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_adadex_and_its_subpackages_is_cheap():
    """Importing the package and every subpackage loads none of torch, TorchRL, tensordict, MuJoCo (the
    names import them on first use), and registers the gymnasium id."""
    code = "import adadex, " + ", ".join(f"adadex.{n}" for n in SUBPACKAGES) + "\nimport gymnasium\n" \
           "assert 'adadex/Tracking-v0' in gymnasium.registry"
    assert _loaded_after(code) == []


def test_a_name_imports_its_module_on_first_use():
    assert "torch" in _loaded_after("from adadex.modules import Tracker")


@pytest.mark.parametrize("package, name", [("adadex.eval", "evaluate"), ("adadex.transforms", "modulation"),
                                           ("adadex.train", "distill"), ("adadex.sysid", "diagnose")])
def test_a_function_named_like_its_module_stays_the_function(package, name):
    """Importing the defining module (before or after) does not replace the exported function."""
    code = (f"import importlib\nimport {package} as p\nm = importlib.import_module('{package}.{name}')\n"
            f"from {package} import {name} as f\nassert callable(f) and f is m.{name}, f\n"
            f"import {package}.{name}\nassert p.{name} is m.{name}")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def test_the_api_reference_is_up_to_date():
    """docs/api.md is what ``python docs/make_api.py`` writes from the ``__all__`` lists and docstrings."""
    import runpy

    make_api = runpy.run_path(str(PACKAGE.parent / "docs" / "make_api.py"))
    assert (PACKAGE.parent / "docs" / "api.md").read_text(encoding="utf-8") == make_api["render"](), \
        "docs/api.md is out of date: run python docs/make_api.py"


def test_every_public_name_has_a_docstring():
    """Each exported class and function says what it is (the API reference's one line)."""
    import inspect

    missing = []
    for name in SUBPACKAGES:
        package = importlib.import_module(f"adadex.{name}")
        for attr in package.__all__:
            obj = inspect.unwrap(getattr(package, attr))
            if (inspect.isclass(obj) or callable(obj)) and not (obj.__doc__ or "").strip():
                missing.append(f"adadex.{name}.{attr}")
    assert not missing, f"no docstring: {missing}"
