"""scipy's k-d tree loaded alone (bopsurg.metrics._kdtree): the same class scipy.spatial
gives, with or without the shortcut, and the rest of scipy.spatial still imports."""

from __future__ import annotations

import subprocess
import sys

from bopsurg.metrics import _kdtree


def test_the_tree_alone_is_scipys_and_scipy_spatial_still_imports():
    code = (
        "import sys; from bopsurg.metrics._kdtree import ckdtree_class; C = ckdtree_class(); "
        "alone = 'scipy.spatial' not in sys.modules; import numpy as np, scipy.spatial as sp; "
        "print(alone, sp.cKDTree is C, sp.ConvexHull(np.eye(4)[:, :3]).vertices.size, "
        "C(np.eye(3)).query([0.9, 0, 0])[1])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True", "4", "0"]


def test_an_unknown_layout_falls_back_to_the_plain_import(monkeypatch):
    def fail() -> None:
        raise ImportError("another layout")

    monkeypatch.setattr(_kdtree, "_load_alone", fail)
    monkeypatch.delitem(sys.modules, "scipy.spatial", raising=False)
    found = _kdtree.ckdtree_class()  # (scipy.spatial not loaded: the shortcut is tried)
    from scipy.spatial import cKDTree

    assert found is cKDTree
