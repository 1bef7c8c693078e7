"""Plugin discovery through entry points, and the interfaces plugins implement.

Built-in plugins (``bopsurg.generators``, ``bopsurg.models``) register under the same
entry-point groups as third-party ones, so there is one discovery path. A third party adds a
plugin from its own distribution::

    [project.entry-points."bopsurg.renderers"]
    myrenderer = "mypkg.render:MyDepthRenderer"

The core only ever reaches a plugin through :func:`load_plugin`, never by import.
"""

from __future__ import annotations

import logging
import sys
from importlib.metadata import EntryPoint, entry_points
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from bopsurg.errors import BopsurgError

if TYPE_CHECKING:
    import numpy as np
    from numpy.typing import NDArray

    from bopsurg.bop.meshes import ObjectModel

log = logging.getLogger(__name__)

#: Entry-point groups, by plugin kind.
GROUPS: dict[str, str] = {
    "renderer": "bopsurg.renderers",
    "backend": "bopsurg.render_backends",
    "estimator": "bopsurg.estimators",
    "command": "bopsurg.commands",
}
#: Former group names still searched (with a deprecation warning), by current group.
DEPRECATED_GROUPS: dict[str, str] = {"bopsurg.render_backends": "bopsurg.generators"}
#: The extra that brings the built-in plugin of each kind.
PLUGIN_EXTRAS: dict[str, str] = {
    "renderer": "bopsurg[vsd]",
    "backend": "bopsurg[sim]",
    "estimator": "bopsurg[torch]",
}
#: The extra that brings each optional module a built-in plugin imports.
MODULE_EXTRAS: dict[str, str] = {
    "pybullet": "bopsurg[vsd]",
    "rosbags": "bopsurg[sim]",
    "torch": "bopsurg[torch]",
}


@runtime_checkable
class DepthRenderer(Protocol):
    """Renders the depth of one object model; what VSD and visibility computation need.

    Implementations must be headless and return z-depth (not distance) in mm, 0 where the
    object is absent, for a pinhole camera with matrix ``K`` and the pose convention of BOP
    (``x_cam = R x + t``, mm).
    """

    def render_depth(
        self,
        model: ObjectModel,
        R: NDArray[np.float64],
        t: NDArray[np.float64],
        K: NDArray[np.float64],
        width: int,
        height: int,
    ) -> NDArray[np.float64]:
        """Render (height, width) depth in mm of ``model`` at pose (R (3, 3), t (3,) mm)."""
        ...


def available_plugins(kind: str) -> dict[str, EntryPoint]:
    """Installed plugins of one kind, by name.

    Args:
        kind: One of :data:`GROUPS` (``"renderer"``, ``"backend"``, ``"estimator"``,
            ``"command"``: a module with ``register(subparsers)`` adding a CLI subcommand).
            Plugins registered under a former group name (:data:`DEPRECATED_GROUPS`) are
            found too, with a warning; the current group wins on a name clash.
    """
    if kind not in GROUPS:
        raise BopsurgError(f"unknown plugin kind {kind!r}; expected one of {sorted(GROUPS)}")
    group = GROUPS[kind]
    found: dict[str, EntryPoint] = {}
    old = DEPRECATED_GROUPS.get(group)
    for ep in entry_points(group=old) if old else ():
        log.warning(
            "plugin %r (%s) is registered under the deprecated entry-point group %r; "
            "register it under %r",
            ep.name,
            ep.value,
            old,
            group,
        )
        found[ep.name] = ep
    found.update({ep.name: ep for ep in entry_points(group=group)})
    return found


def load_plugin(
    kind: str, name: str | None = None, *, installed: dict[str, EntryPoint] | None = None
) -> Any:
    """Load a plugin object (class or factory) by kind and name.

    Args:
        kind: Plugin kind (see :data:`GROUPS`).
        name: Entry-point name; ``None`` takes the first installed one in name order.
        installed: :func:`available_plugins` of ``kind``, when the caller has them already
            (each call reads every installed distribution's entry points).

    Returns:
        The loaded object.

    Raises:
        BopsurgError: No such plugin is installed, or it fails to import (e.g. its optional
            dependencies are missing); the message says which extra to install.
    """
    plugins = available_plugins(kind) if installed is None else installed
    if not plugins:
        raise BopsurgError(
            f"no {kind} plugin is installed (group {GROUPS[kind]!r}); "
            f"install {PLUGIN_EXTRAS.get(kind, 'bopsurg[all]')} for the built-in one"
        )
    if name is None:
        name = sorted(plugins)[0]
    if name not in plugins:
        raise BopsurgError(f"no {kind} plugin named {name!r}; installed: {sorted(plugins)}")
    try:
        return plugins[name].load()
    except ImportError as err:
        hint = install_hint(err.name) if err.name else ""
        raise BopsurgError(f"{kind} plugin {name!r} cannot be imported: {err}{hint}") from err


def install_hint(module: str) -> str:
    """``"; pip install 'bopsurg[EXTRA]'"`` for an optional module (with pybullet's Python
    versions: it ships wheels for CPython 3.10 and 3.11 only), or ``""``."""
    extra = MODULE_EXTRAS.get(module.partition(".")[0])
    if extra is None:
        return ""
    hint = f"; pip install '{extra}'"
    if module.startswith("pybullet") and sys.version_info >= (3, 12):
        hint += (
            " (pybullet has wheels for Python 3.10 and 3.11 only: on this Python pip builds it "
            "from source, which needs a C++ compiler and the Python headers)"
        )
    return hint
