"""Folders written by ``bopsurg eval``, read back for the figures and the rerun recording of
``bopsurg compare``.

A comparison draws every evaluation on the same axes and the same ``frame`` timeline, which
is only meaningful for evaluations of the same test set: :func:`load_eval_folders` refuses
folders without ``errors.csv`` (e.g. COCO evaluations) and evaluations of different test sets
with a one-line :class:`~bopsurg.errors.BopsurgError`.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from bopsurg.bop.dataset import BopDataset
from bopsurg.errors import BopsurgError
from bopsurg.evaluation.bootstrap import SAMPLES_FILENAME, DetectionSamples
from bopsurg.evaluation.summary_ci import TABLE_SAMPLES_FILENAME, load_table_rows
from bopsurg.evaluation.tables import load_gt_table

log = logging.getLogger(__name__)

#: Columns of errors.csv that the figures and the recording need.
REQUIRED_COLUMNS = ("scene_id", "im_id", "gt_id", "visib_fract", "mssd")
_KEY = ["scene_id", "im_id", "gt_id"]


@dataclass(frozen=True)
class EvalFolder:
    """One evaluation of a comparison.

    Attributes:
        path: The folder written by ``bopsurg eval``.
        label: Its name in legends and reports (the folder's name, or its path when two
            compared folders share a name).
        key: ``label`` reduced to ``[A-Za-z0-9_-]`` and made unique: its rerun entity-path part.
        errors: errors.csv (one row per estimate; RE deg, TE / MSSD / ADD mm, MSPD px).
        summary: summary.json (``min_visib``, ``gt_instances``, the paper's table, ...).
        detections: The BOP24 samples (``bootstrap_bop24.npz``), None without the bop24 task.
        table_rows: The paper's table's GT instances (``bootstrap_table.npz``), None if absent.
    """

    path: Path
    label: str
    key: str
    errors: pd.DataFrame
    summary: dict[str, Any]
    detections: DetectionSamples | None
    table_rows: pd.DataFrame | None


def method_labels(paths: Sequence[Path]) -> list[str]:
    """Folder names, or the paths as given when two folders share a name."""
    names = [Path(p).name or str(p) for p in paths]
    return names if len(set(names)) == len(names) else [str(p) for p in paths]


def entity_keys(labels: Sequence[str]) -> list[str]:
    """Labels as rerun entity-path parts: ``[A-Za-z0-9_-]`` only, unique (``_2``, ... added)."""
    keys: list[str] = []
    for label in labels:
        key = re.sub(r"[^A-Za-z0-9_-]+", "_", label).strip("_") or "eval"
        base, n = key, 2
        while key in keys:
            key, n = f"{base}_{n}", n + 1
        keys.append(key)
    return keys


def _read_json(path: Path) -> dict[str, Any]:
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise BopsurgError(f"{path}: missing (not a folder written by 'bopsurg eval')") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BopsurgError(f"{path}: unreadable ({exc})") from None
    if not isinstance(value, dict):
        raise BopsurgError(f"{path}: not the summary of 'bopsurg eval' (not an object)")
    return value


def load_eval_folder(path: Path, label: str, key: str | None = None) -> EvalFolder:
    """Read one evaluation folder (errors.csv, summary.json, the bootstrap samples).

    Raises:
        BopsurgError: No errors.csv (not an evaluation of pose results), missing columns,
            or an unreadable file.
    """
    path = Path(path)
    csv = path / "errors.csv"
    if not path.is_dir():
        raise BopsurgError(f"{path}: not a folder")
    if not csv.is_file():
        raise BopsurgError(
            f"{csv}: missing (figures and recordings of a comparison need evaluations of "
            "pose results by 'bopsurg eval')"
        )
    try:
        errors = pd.read_csv(csv)
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise BopsurgError(f"{csv}: unreadable ({exc})") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in errors]
    if missing:
        raise BopsurgError(f"{csv}: not errors.csv of 'bopsurg eval' (no {', '.join(missing)})")
    summary = _read_json(path / "summary.json")
    for field in ("min_visib", "gt_instances"):
        if not isinstance(summary.get(field), int | float):
            raise BopsurgError(f"{path / 'summary.json'}: no number '{field}'")
    det = (
        DetectionSamples.load(path / SAMPLES_FILENAME)
        if (path / SAMPLES_FILENAME).exists()
        else None
    )
    table = path / TABLE_SAMPLES_FILENAME
    rows = load_table_rows(table) if table.exists() else None
    return EvalFolder(path, label, key or entity_keys([label])[0], errors, summary, det, rows)


def load_eval_folders(paths: Sequence[Path]) -> list[EvalFolder]:
    """Read the compared evaluation folders (the first is the baseline) and check that they
    evaluate the same test set: the same split, ``--min-visib``, number of GT instances and,
    where both folders hold them, the same GT instances in the paper's table.

    Raises:
        BopsurgError: A folder cannot be read (:func:`load_eval_folder`), or two folders
            are evaluations of different test sets.
    """
    paths = [Path(p) for p in paths]
    labels = method_labels(paths)
    folders = [
        load_eval_folder(p, lab, k)
        for p, lab, k in zip(paths, labels, entity_keys(labels), strict=True)
    ]
    base = folders[0]
    for other in folders[1:]:
        why = _test_set_difference(base, other)
        if why:
            raise BopsurgError(
                f"{base.path} and {other.path} are evaluations of different test sets ({why})"
            )
    return folders


def _test_set_difference(a: EvalFolder, b: EvalFolder) -> str | None:
    """Why two evaluations are not of the same test set, None when nothing tells them apart."""
    split_a, split_b = a.summary.get("split"), b.summary.get("split")
    if split_a is not None and split_b is not None and split_a != split_b:
        return f"split {split_a} vs {split_b}"
    if a.summary["min_visib"] != b.summary["min_visib"]:
        return f"--min-visib {a.summary['min_visib']:g} vs {b.summary['min_visib']:g}"
    if a.summary["gt_instances"] != b.summary["gt_instances"]:
        return f"{a.summary['gt_instances']} vs {b.summary['gt_instances']} GT instances"
    if a.table_rows is not None and b.table_rows is not None:
        ka, kb = a.table_rows[_KEY].to_numpy(), b.table_rows[_KEY].to_numpy()
        if ka.shape != kb.shape or not np.array_equal(ka, kb):
            return "not the same GT instances"
    return None


def gt_distributions_of(dataset: BopDataset) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The split's GT camera distances (mm) and the visible fractions where known (Fig. 2)."""
    gt = load_gt_table(dataset, need_gt_info=False)
    distance = np.linalg.norm(gt.t, axis=1)
    visib = gt.visib_fract[np.isfinite(gt.visib_fract)]
    return distance.astype(np.float64), visib.astype(np.float64)


def comparison_gt(
    folders: Sequence[EvalFolder],
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """The GT distances (mm) and visible fractions of the compared test set, read from the
    dataset each summary.json names (one Fig. 2: every such dataset that is still there must
    give the same values). None when none of them can be read.

    Raises:
        BopsurgError: Two of the datasets differ.
    """
    seen: dict[tuple[str, str], tuple[NDArray[np.float64], NDArray[np.float64]]] = {}
    first: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    first_src = ""
    for f in folders:
        root, split = f.summary.get("dataset"), f.summary.get("split", "test")
        if not isinstance(root, str) or not isinstance(split, str):
            continue
        src = (root, split)
        if src in seen or not (Path(root) / split).is_dir():
            continue
        try:
            seen[src] = gt_distributions_of(BopDataset(root, split))
        except BopsurgError as err:
            log.info("Fig. 2: %s/%s not read (%s)", root, split, err)
            continue
        if first is None:
            first, first_src = seen[src], f"{root} ({split})"
        elif any(
            x.shape != y.shape or not np.allclose(x, y)
            for x, y in zip(first, seen[src], strict=True)
        ):
            raise BopsurgError(
                f"{first_src} and {root} ({split}) hold different GT: the evaluations are not "
                "of the same test set"
            )
    if first is None:
        log.info("Fig. 2 skipped: the evaluated dataset (summary.json 'dataset') is not there")
    return first
