"""Arguments and loading shared by the commands that take a dataset and a results CSV."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from bopsurg.evaluation.options import CI_UNITS, DEFAULT_REPLICATES

if TYPE_CHECKING:  # imported in the functions: building the parser stays light
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.bop.results import PoseEstimates
    from bopsurg.estimation import Detections


def add_dataset(p: argparse.ArgumentParser, *, results: bool = False) -> None:
    """``DATASET [RESULTS] --split --split-type --dataset``."""
    p.add_argument("dataset", help="dataset root folder (holds models/ and the split folders)")
    if results:
        p.add_argument("results", help="BOP19 results CSV: scene_id,im_id,obj_id,score,R,t,time")
    p.add_argument("--split", default="test", help="split folder name (default: test)")
    p.add_argument("--split-type", default=None, help="split type suffix, e.g. pbr for train_pbr")
    p.add_argument(
        "--dataset",
        dest="dataset_name",
        metavar="NAME",
        default=None,
        help="a standard BOP dataset's defaults (lmo, tless, ycbv, itodd, hot3d ...; 'none': "
        "no defaults); default: the one the folder's name matches (docs/datasets.md)",
    )


def add_dataset_and_results(p: argparse.ArgumentParser) -> None:
    """``DATASET RESULTS --split --split-type --dataset``."""
    add_dataset(p, results=True)


def load_dataset_and_results(args: argparse.Namespace) -> tuple[BopDataset, PoseEstimates]:
    """Open the dataset, load the results and check them against it (one-line errors)."""
    from bopsurg.bop.dataset import BopDataset
    from bopsurg.bop.results import check_results_against_dataset, load_results

    dataset = BopDataset(
        args.dataset, args.split, split_type=args.split_type, name=args.dataset_name
    )
    results_path = Path(args.results)
    est = load_results(results_path)
    images = {(s, i) for s in dataset.scene_ids for i in dataset.scene(s).camera}
    check_results_against_dataset(est, results_path, images=images, obj_ids=set(dataset.obj_ids))
    return dataset, est


def key_value(text: str) -> tuple[str, str]:
    """argparse type of a ``KEY=VALUE`` option (``--option``, ``--backend-option``)."""
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key, value


def add_executor_args(p: argparse.ArgumentParser, *, unit: str) -> None:
    """``--executor local|ray --workers N --ray-address ADDR`` (see bopsurg.executors)."""
    p.add_argument(
        "--executor",
        choices=("local", "ray"),
        default="local",
        help=f"where the {unit}s run: local worker processes (default) or a Ray cluster "
        "(pip install bopsurg[ray]; datasets on a path every node sees)",
    )
    p.add_argument("--workers", type=int, default=1, help="local worker processes (default: 1)")
    p.add_argument(
        "--ray-address",
        default=None,
        metavar="HOST:PORT",
        help="Ray cluster to join (default: start a local Ray instance)",
    )


def add_detections_arg(p: argparse.ArgumentParser) -> None:
    """``--detections FILE.json``: 2D boxes to draw in the rerun recording."""
    p.add_argument(
        "--detections",
        default=None,
        metavar="FILE.json",
        help="BOP detections JSON (e.g. from 'bopsurg predict --detections-out') whose boxes "
        "are drawn in the rerun recording",
    )


def load_detections_arg(args: argparse.Namespace) -> dict[tuple[int, int], Detections] | None:
    """The boxes of ``--detections``, or None."""
    if not getattr(args, "detections", None):
        return None
    from bopsurg.bop.detections import load_detections

    return load_detections(args.detections)[0]


def _replicates(text: str) -> int:
    """``--bootstrap`` value: a non-negative integer (argparse reports a bad one)."""
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a number of replicates >= 0, got {text!r}")
    return n


def add_bootstrap_args(p: argparse.ArgumentParser) -> None:
    """The options of the bootstrap intervals (shared by ``eval`` and ``compare``)."""
    p.add_argument(
        "--bootstrap",
        type=_replicates,
        default=DEFAULT_REPLICATES,
        metavar="N",
        help=f"bootstrap replicates of the 95 %% intervals (default: {DEFAULT_REPLICATES}; "
        "0 = no intervals)",
    )
    p.add_argument(
        "--ci-unit",
        choices=CI_UNITS,
        default="image",
        help="what the bootstrap resamples: target images, or whole scenes when images of a "
        "scene are correlated (consecutive video frames) (default: image)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the bootstrap (default: 0)")
