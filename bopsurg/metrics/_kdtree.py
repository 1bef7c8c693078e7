"""scipy's k-d tree without the rest of ``scipy.spatial``.

ADD-S (:func:`bopsurg.metrics.pose_error.adi`) needs ``cKDTree`` only, but importing
``scipy.spatial`` also imports Qhull, ``scipy.linalg``, ``scipy.special`` and the rotations,
more than half of its cost and a large share of ``bopsurg eval`` on a small split. The tree's
compiled module is loaded on its own when ``scipy.spatial`` is not imported yet; it is the
same module that ``scipy.spatial`` imports later (it finds it loaded). Any surprise (another
scipy layout) falls back to the plain import.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path
from typing import Any

_MODULE = "scipy.spatial._ckdtree"


def ckdtree_class() -> Any:
    """``scipy.spatial.cKDTree``."""
    if "scipy.spatial" not in sys.modules:
        try:
            return _load_alone().cKDTree
        except Exception:  # any scipy layout we do not know: the plain import
            sys.modules.pop(_MODULE, None)
    from scipy.spatial import cKDTree

    return cKDTree


def _load_alone() -> Any:
    """The k-d tree's extension module, loaded without running ``scipy.spatial``'s
    ``__init__`` (registered under its own name, so that a later import reuses it)."""
    loaded = sys.modules.get(_MODULE)
    if loaded is not None:
        return loaded
    import scipy

    folder = Path(scipy.__file__).parent / "spatial"
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        path = folder / f"_ckdtree{suffix}"
        if path.is_file():
            break
    else:
        raise ImportError(f"no {_MODULE} extension in {folder}")
    loader = importlib.machinery.ExtensionFileLoader(_MODULE, str(path))
    spec = importlib.util.spec_from_file_location(_MODULE, path, loader=loader)
    if spec is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[_MODULE] = module
    loader.exec_module(module)
    return module
