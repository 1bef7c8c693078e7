"""Packages that import their modules on first access (bopsurg._lazy): every exported name
resolves to its module's object, and importing the package (or eval's parser, or the VSD
worker's module) loads no numpy."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.parametrize("package", ["bopsurg.bop", "bopsurg.metrics"])
def test_every_exported_name_is_its_modules_object(package):
    pkg = importlib.import_module(package)
    for name in pkg.__all__:
        home = pkg._HOME[name]
        assert getattr(pkg, name) is getattr(importlib.import_module(home, package), name)
        assert name in dir(pkg)
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        pkg.nope  # noqa: B018


def test_a_name_shared_with_its_module_stays_the_export():
    import bopsurg.metrics
    import bopsurg.metrics.vsd  # binds the submodule on the package, as an import does
    from bopsurg.metrics import vsd

    assert callable(vsd)
    assert vsd is sys.modules["bopsurg.metrics.vsd"].vsd
    assert bopsurg.metrics.vsd is vsd


def test_the_light_imports_load_no_numpy():
    code = (
        "import sys; import bopsurg.bop, bopsurg.metrics, bopsurg.metrics.registry, "
        "bopsurg.cli.eval_cmd, bopsurg.evaluation.vsd_worker; "
        "print(sorted(m for m in ('numpy', 'pandas', 'cv2') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize("package", ["bopsurg.bop", "bopsurg.metrics"])
def test_the_three_lists_of_exports_agree(package):
    """``__all__``, the lazy homes and the ``TYPE_CHECKING`` imports (what mypy and editors
    see) name the same objects in the same modules: an export added to one list only fails."""
    import ast

    pkg = importlib.import_module(package)
    tree = ast.parse(Path(pkg.__file__).read_text(encoding="utf-8"))
    typed: dict[str, str] = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and getattr(node.test, "id", None) == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom)
                for alias in imp.names:
                    typed[alias.asname or alias.name] = imp.module.removeprefix(package)
    assert sorted(pkg.__all__) == sorted(pkg._HOME) == sorted(typed)
    assert typed == pkg._HOME
