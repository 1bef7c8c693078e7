"""Checkpoints: a weights-only state dict (``NAME.pt``) beside a JSON config (``NAME.json``).

The ``.pt`` file holds tensors only and is read with ``torch.load(weights_only=True)``, so a
checkpoint from an untrusted source cannot run code. Everything needed to rebuild the model
(architecture config, object id, normalisation, training provenance) is plain JSON next to it.
Both files are written atomically. Shipped weights are stored as float16 (half the size) and
cast back to float32 on load.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from torch import nn

from bopsurg.atomic import atomic_path, write_text
from bopsurg.errors import CheckpointError

#: Version of the JSON layout.
FORMAT = 1


def config_path(path: str | Path) -> Path:
    """The JSON twin of a ``.pt`` file."""
    return Path(path).with_suffix(".json")


def save_checkpoint(
    path: str | Path,
    state: dict[str, torch.Tensor],
    *,
    kind: str,
    config: dict[str, Any],
    meta: dict[str, Any] | None = None,
    half: bool = False,
) -> None:
    """Write ``path`` (weights) and its ``.json`` twin (kind, config, meta), atomically.

    Args:
        path: The ``.pt`` file.
        state: A model's ``state_dict()``.
        kind: What the weights are for (``"detector"``, ``"pose"``), checked on load.
        config: JSON-safe architecture config that rebuilds the model.
        meta: JSON-safe extras (object id, normalisation, training command and seed ...).
        half: Store floating-point tensors as float16.
    """
    tensors = {
        k: (v.detach().to("cpu").half() if half and v.is_floating_point() else v.detach().cpu())
        for k, v in state.items()
    }
    with atomic_path(path) as tmp:
        torch.save(tensors, tmp)
    info = {"format": FORMAT, "kind": kind, "config": config, "meta": meta or {}}
    write_text(config_path(path), json.dumps(info, indent=2, sort_keys=True) + "\n")


def load_checkpoint(path: str | Path, kind: str) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Returns:
        ``(state, info)``: float32 tensors on the CPU and the JSON content
        (``info["config"]``, ``info["meta"]``).

    Raises:
        CheckpointError: A file is missing or corrupt, or it holds another kind of model.
    """
    path = Path(path)
    twin = config_path(path)
    if not path.is_file():
        raise CheckpointError("checkpoint not found", path=path)
    if not twin.is_file():
        raise CheckpointError("its JSON config is missing (expected beside it)", path=twin)
    try:
        info = json.loads(twin.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise CheckpointError(f"not valid JSON ({err})", path=twin) from err
    if not isinstance(info, dict) or not isinstance(info.get("config"), dict):
        raise CheckpointError("expected an object with a 'config' object", path=twin)
    if info.get("kind") != kind:
        raise CheckpointError(f"holds a {info.get('kind')!r} model, expected {kind!r}", path=twin)
    state = load_tensors(path)
    return {k: v.float() if v.is_floating_point() else v for k, v in state.items()}, info


def load_tensors(path: str | Path) -> dict[str, Any]:
    """``torch.load(weights_only=True)`` on the CPU with one-line errors."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError as err:
        raise CheckpointError("checkpoint not found", path=path) from err
    except Exception as err:  # torch raises many exception types for corrupt files
        reason = " ".join(str(err).split())[:200]
        raise CheckpointError(
            f"corrupt or not a weights-only checkpoint ({reason})", path=path
        ) from err
    if not isinstance(state, dict):
        raise CheckpointError(f"expected a dict of tensors, got {type(state).__name__}", path=path)
    return state


def load_weights(model: nn.Module, state: dict[str, torch.Tensor], path: str | Path) -> None:
    """``model.load_state_dict(state, strict=True)`` with a one-line error on mismatch."""
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as err:
        first = str(err).strip().splitlines()
        detail = " ".join(" ".join(first[:3]).split())[:300]
        raise CheckpointError(
            f"does not fit the model its config describes: {detail}", path=path
        ) from err
