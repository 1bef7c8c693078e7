"""What the estimator benches share: running a bopsurg command in-process, predict + eval of a
split, the arguments of a bench on a dataset split (``--predict-option`` among them), the
needles the paper's table counts, oracle boxes, and a split's images decoded for timing an
estimator in-process."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import time
from pathlib import Path

import pandas as pd

from bopsurg import prediction
from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.detections import gt_detections, save_detections
from bopsurg.cli.main import main as bopsurg
from bopsurg.estimation import ImageInput, PoseEstimator

#: RE above which a needle's tip and tail count as swapped, deg.
FLIP_DEG = 90.0


def run(argv: list[str], *, quiet: bool = False) -> float:
    """One bopsurg command; returns its wall time in s. ``quiet``: drop what it prints (its
    log lines, e.g. the model-frame mapping, still go to stderr)."""
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()) if quiet else contextlib.nullcontext():
        code = bopsurg(argv)
    if code:
        raise SystemExit(f"bopsurg {' '.join(argv)} failed with exit code {code}")
    return time.perf_counter() - t0


def evaluate(data: Path, results: Path, ev: Path, *, split: str = "test") -> dict:
    """Evaluate; returns summary, scores and the per-estimate errors."""
    shutil.rmtree(ev, ignore_errors=True)
    argv = ["eval", str(data), str(results), "--split", split, "--out", str(ev), "--no-progress"]
    run(argv, quiet=True)
    return {
        "summary": json.loads((ev / "summary.json").read_text()),
        "scores": json.loads((ev / "scores.json").read_text()),
        "errors": pd.read_csv(ev / "errors.csv"),
    }


def predict_eval(
    data: Path, split: str, out: Path, key: str, device: str, argv: list[str]
) -> tuple[dict, pd.DataFrame, float]:
    """``bopsurg predict`` (extra arguments ``argv``) into OUT/results_KEY.csv, then ``bopsurg
    eval`` into OUT/eval_KEY. Returns the evaluation (summary, scores), its per-estimate
    errors and the prediction's wall time in s."""
    results = out / f"results_{key}.csv"
    seconds = run(
        ["predict", str(data), "--split", split, "--out", str(results), "--device", device,
         "--no-progress", *argv], quiet=True,
    )  # fmt: skip
    ev = evaluate(data, results, out / f"eval_{key}", split=split)
    return ev, ev.pop("errors"), seconds


def table_needles(ev: dict, errors: pd.DataFrame) -> pd.DataFrame:
    """The matched estimates of the GT instances the paper's table counts (visib_fract >= the
    evaluation's min_visib)."""
    return errors[(errors.visib_fract >= ev["summary"]["min_visib"]) & (errors.gt_id >= 0)]


def split_bench_parser(doc: str | None, data_help: str, example: str) -> argparse.ArgumentParser:
    """The arguments of a bench on a dataset split: DATA, --split, --out, --device and
    ``--predict-option``."""
    ap = argparse.ArgumentParser(
        description=doc, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("data", type=Path, help=data_help)
    ap.add_argument("--split", default="test")
    ap.add_argument("--out", type=Path, required=True, help="work folder (rewritten)")
    ap.add_argument("--device", default="cpu")
    add_predict_option(ap, example)
    return ap


def fresh_dir(path: Path) -> Path:
    """``path`` emptied (a bench's work folder is rewritten)."""
    shutil.rmtree(path, ignore_errors=True)
    path.mkdir(parents=True)
    return path


def add_predict_option(ap: argparse.ArgumentParser, example: str) -> None:
    """``--predict-option KEY=VALUE`` (repeatable): passed on to ``bopsurg predict --option``."""
    ap.add_argument(
        "--predict-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help=f"passed to bopsurg predict --option (e.g. {example})",
    )


def predict_options(options: list[str]) -> list[str]:
    """``bopsurg predict`` arguments for ``--predict-option`` values."""
    return [x for o in options for x in ("--option", o)]


def oracle_boxes(data: Path, split: str, path: Path) -> Path:
    """Write the GT visible boxes of a split as detections (score 1) to ``path``: a pose
    stage run on them is measured without its detector's misses."""
    dets = gt_detections(BopDataset(data, split))
    save_detections(path, dets, dict.fromkeys(dets, 0.0))
    return path


def decoded_images(
    ds: BopDataset, estimator: PoseEstimator, count: int, depth: bool
) -> tuple[prediction._Mapped, list[ImageInput]]:
    """The estimator as ``bopsurg predict`` runs it on ``ds`` (its poses mapped to the split's
    models; depth images given with ``depth``), and the split's first ``count`` target images
    decoded as predict gives them to it: what a bench times ``predict_batch`` on, decoding
    excluded."""
    maps = prediction.dataset_mappings(ds, estimator)
    mapped = prediction._Mapped(estimator, maps, depth)
    todo = prediction.image_targets(ds, mapped.obj_ids)
    div = prediction.depth_divisor(maps) if depth else None
    keys = list(todo)[:count]
    return mapped, [prediction._load_image(ds, k, todo[k], None, div) for k in keys]
