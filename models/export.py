"""Export the built-in networks to ONNX, each with a JSON of what running it needs.

``bopsurg export`` (:mod:`.cli_export`) writes, per checkpoint, ``NAME.onnx`` and ``NAME.json``
into one folder: the detector (:class:`~.detector.model.YoloxDetector`, raw predictions), the
pose heads (:class:`~.pose.network.GdrPoseNet`, its five outputs) and the needle segmenter
(:class:`~.refine.seghead.NeedleSegNet`, mask logits). Each JSON holds the input and output
names and shapes, the pre- and post-processing constants (classes, input size, letterbox
grey, the xyz normaliser, crop padding, zoom, the needle's arc) and the source checkpoint's
SHA-256, so :mod:`.onnx_runtime` runs the exported pipeline with numpy and onnxruntime alone.

Exporter: torch's TorchScript-based exporter (``dynamo=False``) by default: it needs only
torch and onnx, runs in seconds, writes the same bytes on every run, and its dynamic axes
make the batch (and the detector's input size) free. ``exporter="dynamo"`` uses the
``torch.export`` path instead, which needs the onnxscript package.
"""

from __future__ import annotations

import hashlib
import io
import json
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from bopsurg.atomic import write_bytes, write_text
from bopsurg.errors import BopsurgError
from bopsurg.models.checkpoint import load_checkpoint, load_weights
from bopsurg.models.detector import DetectorConfig, YoloxDetector
from bopsurg.models.detector.letterbox import PAD_GREY
from bopsurg.models.detector.model import PRE_NMS_TOP_K
from bopsurg.models.pose.config import PoseConfig
from bopsurg.models.pose.network import GdrPoseNet
from bopsurg.models.predict_config import HeadSettings
from bopsurg.models.refine.seghead import NeedleSegNet, SegConfig

#: Version of the JSON written beside each .onnx (bump when a key changes meaning).
META_FORMAT = 1
#: ONNX opset: 17 has every operator the three networks use (GroupNorm is decomposed).
DEFAULT_OPSET = 17
EXPORTERS = ("torchscript", "dynamo")
#: Agreement required between onnxruntime and torch on the seeded sample inputs.
CHECK_ATOL = 1e-4
#: Batch of the sample inputs the export traces (the checks use another batch size, so the
#: dynamic batch axis is exercised).
TRACE_BATCH = 2
CHECK_BATCH = 3
#: The detector's post-processing defaults (:meth:`YoloxDetector.detect`), recorded so the
#: runner decodes as the estimator does.
DETECT_DEFAULTS = {"conf": 0.05, "nms_iou": 0.65, "max_det": 100, "pre_nms_top_k": PRE_NMS_TOP_K}


@dataclass
class Exportable:
    """A network ready for export: the module in eval mode, named inputs and outputs, the
    axes that stay free, seeded sample inputs and the metadata for its JSON."""

    name: str
    kind: str
    net: nn.Module
    input_names: list[str]
    output_names: list[str]
    dynamic_axes: dict[str, dict[int, str]]
    sample: Any  # callable batch -> tuple of input tensors
    meta: dict[str, Any] = field(default_factory=dict)

    def inputs(self, batch: int) -> tuple[torch.Tensor, ...]:
        """Seeded sample inputs of ``batch`` items (uniform in [0, 1))."""
        out: tuple[torch.Tensor, ...] = self.sample(batch)
        return out


def _rand(seed: int, *shape: int) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed))


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _bad(path: Path, what: str, err: Exception) -> BopsurgError:
    return BopsurgError(f"{path.with_suffix('.json')}: bad {what} config ({err})")


def load_detector(path: str | Path) -> Exportable:
    """The detector checkpoint ``path`` as an :class:`Exportable`: input ``images`` (B, 3, H,
    W) RGB in [0, 1] letterboxed (H, W free, multiples of 32), output ``raw`` (B, A, 5 + C)."""
    path = Path(path)
    state, info = load_checkpoint(path, "detector")
    try:
        cfg = DetectorConfig.from_dict(info["config"])
        classes = [int(c) for c in info["meta"]["classes"]]
    except (KeyError, TypeError, ValueError) as err:
        raise _bad(path, "detector", err) from err
    net = YoloxDetector(cfg)
    load_weights(net, state, path)
    h, w = cfg.input_hw
    meta: dict[str, Any] = {
        "classes": classes,
        "input_hw": [h, w],
        "strides": list(cfg.strides),
        "letterbox": {"pad_grey": PAD_GREY, "anchor": "top-left"},
        "normalise": "RGB uint8 / 255, NCHW float32",
        "raw": "tx, ty, tw, th, objectness logit, class logits; levels in stride order, "
        "cells row-major",
        "detect": dict(DETECT_DEFAULTS),
    }
    return Exportable(
        path.stem, "detector", net.eval(), ["images"], ["raw"],
        {"images": {0: "batch", 2: "height", 3: "width"}, "raw": {0: "batch", 1: "anchors"}},
        lambda b: (_rand(b, b, 3, h, w),), meta,
    )  # fmt: skip


def load_pose_head(path: str | Path) -> Exportable:
    """The pose-head checkpoint ``path``: inputs ``roi_img`` (B, 3, S_in, S_in) RGB in [0, 1]
    and ``roi_coord2d`` (B, 2, S_out, S_out); outputs ``mask``, ``xyz``, ``region``, ``rot6d``
    (allocentric) and ``site`` as :meth:`GdrPoseNet.forward` returns them."""
    path = Path(path)
    state, info = load_checkpoint(path, "pose")
    try:
        cfg = PoseConfig.from_dict(info["config"])
        m = info["meta"]
        meta: dict[str, Any] = {
            "obj_id": int(m["obj_id"]),
            "normaliser": {
                "xyz_centre_mm": [float(v) for v in m["xyz_centre"]],
                "xyz_scale_mm": float(m["xyz_scale"]),
            },
        }
    except (KeyError, TypeError, ValueError) as err:
        raise _bad(path, "pose", err) from err
    net = GdrPoseNet(cfg)
    load_weights(net, state, path)
    s_in, s_out = cfg.roi_in, cfg.roi_out
    meta |= {
        "roi_in": s_in,
        "roi_out": s_out,
        "dzi_pad": cfg.dzi_pad,
        "z_unit_mm": cfg.z_unit_mm,
        "mask_loss": cfg.mask_loss,
        "zoom": list(HeadSettings().zoom),
        "diameter_mm": m.get("diameter"),
        "model_ply": m.get("model_ply"),
        "normalise": "RGB uint8 / 255, NCHW float32",
    }
    outs = ["mask", "xyz", "region", "rot6d", "site"]
    axes = {n: {0: "batch"} for n in ["roi_img", "roi_coord2d", *outs]}
    return Exportable(
        path.stem, "pose", net.eval(), ["roi_img", "roi_coord2d"], outs, axes,
        lambda b: (_rand(b, b, 3, s_in, s_in), _rand(b + 100, b, 2, s_out, s_out)), meta,
    )  # fmt: skip


def load_segmenter(path: str | Path) -> Exportable:
    """The needle-segmenter checkpoint ``path``: input ``roi`` (B, 3, S, S) RGB in [0, 1],
    output ``logits`` (B, C, S, S) (channel 0 visible mask, 1 the full mask with ``amodal``)."""
    path = Path(path)
    state, info = load_checkpoint(path, "needle_seg")
    try:
        cfg = SegConfig.from_dict(info["config"])
        arc = info["meta"]["arc"]
        meta: dict[str, Any] = {
            "arc": {"radius_mm": float(arc["radius"]), "arc_rad": float(arc["arc_rad"])}
        }
    except (KeyError, TypeError, ValueError) as err:
        raise _bad(path, "segmenter", err) from err
    net = NeedleSegNet(cfg)
    load_weights(net, state, path)
    meta |= {
        "roi": cfg.roi,
        "pad": cfg.pad,
        "amodal": cfg.amodal,
        "frame": cfg.frame,
        "channels": cfg.channels,
        "normalise": "RGB uint8 / 255, NCHW float32",
    }
    s = cfg.roi
    axes = {"roi": {0: "batch"}, "logits": {0: "batch"}}
    return Exportable(
        path.stem, "needle_seg", net.eval(), ["roi"], ["logits"], axes,
        lambda b: (_rand(b, b, 3, s, s),), meta,
    )  # fmt: skip


def onnx_bytes(
    item: Exportable, opset: int = DEFAULT_OPSET, exporter: str = "torchscript"
) -> bytes:
    """The ONNX model of ``item`` (traced on :data:`TRACE_BATCH` seeded inputs)."""
    if exporter not in EXPORTERS:
        raise BopsurgError(f"export: exporter must be one of {EXPORTERS}, got {exporter!r}")
    args = item.inputs(TRACE_BATCH)
    with torch.no_grad(), warnings.catch_warnings():
        # torch flags the TorchScript path as deprecated, and tracing warns about the shape
        # checks it turns into constants: both are expected here
        warnings.simplefilter("ignore")
        if exporter == "torchscript":
            buf = io.BytesIO()
            torch.onnx.export(
                item.net, args, buf,  # type: ignore[arg-type]  # a file object works too
                dynamo=False, opset_version=opset,
                input_names=item.input_names, output_names=item.output_names,
                dynamic_axes=item.dynamic_axes, do_constant_folding=True,
            )  # fmt: skip
            return buf.getvalue()
        return _dynamo_bytes(item, args, opset)


def _dynamo_bytes(item: Exportable, args: tuple[torch.Tensor, ...], opset: int) -> bytes:
    try:
        import onnxscript  # noqa: F401
    except ImportError as err:
        raise BopsurgError(
            "export: exporter=dynamo needs onnxscript (pip install onnxscript)"
        ) from err
    shapes = tuple(
        {k: torch.export.Dim(v) for k, v in item.dynamic_axes[n].items() if v == "batch"}
        for n in item.input_names
    )
    program = torch.onnx.export(
        item.net, args, dynamo=True, opset_version=opset, dynamic_shapes=shapes,
        input_names=item.input_names, output_names=item.output_names, optimize=True,
    )  # fmt: skip
    if program is None:
        raise BopsurgError("export: the dynamo exporter returned no program")
    raw: bytes = program.model_proto.SerializeToString()
    return raw


def torch_outputs(item: Exportable, inputs: Sequence[torch.Tensor]) -> list[np.ndarray]:
    """The torch module's outputs on ``inputs``, in :attr:`Exportable.output_names` order."""
    with torch.no_grad():
        out = item.net(*inputs)
    if isinstance(out, dict):
        return [out[n].numpy() for n in item.output_names]
    return [out.numpy()]


def max_difference(onnx_path: str | Path, item: Exportable, batch: int = CHECK_BATCH) -> float:
    """Largest absolute difference between onnxruntime's and torch's outputs on seeded sample
    inputs of ``batch`` items (every output, every element)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    inputs = item.inputs(batch)
    feed = {n: x.numpy() for n, x in zip(item.input_names, inputs, strict=True)}
    got = sess.run(item.output_names, feed)
    want = torch_outputs(item, inputs)
    return max(float(np.abs(g - w).max()) for g, w in zip(got, want, strict=True))


def write_export(
    item: Exportable,
    out_dir: str | Path,
    *,
    source: str | Path,
    opset: int = DEFAULT_OPSET,
    exporter: str = "torchscript",
) -> Path:
    """Write ``NAME.onnx`` and ``NAME.json`` (metadata) into ``out_dir``; returns the .onnx."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    onnx_path = out / f"{item.name}.onnx"
    write_bytes(onnx_path, onnx_bytes(item, opset, exporter))
    meta = {
        "format": META_FORMAT,
        "kind": item.kind,
        "onnx": onnx_path.name,
        "inputs": item.input_names,
        "outputs": item.output_names,
        "dynamic_axes": {
            k: {str(a): n for a, n in v.items()} for k, v in item.dynamic_axes.items()
        },
        "opset": opset,
        "exporter": exporter,
        "torch": torch.__version__,
        "source": {"checkpoint": Path(source).name, "sha256": _sha256(Path(source))},
        **item.meta,
    }
    write_text(out / f"{item.name}.json", json.dumps(meta, indent=2, sort_keys=True) + "\n")
    return onnx_path
