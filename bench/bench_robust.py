"""Bench: a model on the sealed test splits of both domains (issue #41), RGB and RGB-D.

Steps, each a `bopsurg` command:

  1. bopsurg data bench/robust_splits.yaml --root OUT/data_SPLIT --only SPLIT   (each test
     split of the file, in a dataset root of its own: predict and eval read the root's
     test targets; the episodes are kept in OUT/bags)
  2. bopsurg predict OUT/data_SPLIT --split SPLIT [--no-depth] --out OUT/results_SPLIT_INPUT.csv
  3. bopsurg eval ... --task bop19 --renderer none --bootstrap 1000 --out OUT/eval_SPLIT_INPUT

then prints the paper's table per domain with 95 % bootstrap intervals by image: median RE,
TE, MSSD, AR_MSSD, the share of needles with RE > 90 deg (tip and tail swapped), N (GT needles
with visib_fract >= 0.3, found / all). With ``--ambf DIR`` the same for frames of the paper's
AMBF pipeline (imported as bench/bench_transfer.py does): a final look, nothing is chosen by
it. Rerun the same command to resume: made splits, predictions and evaluations are reused
(remove OUT/results_* and OUT/eval_* after changing the model).

    python bench/bench_robust.py --out runs/robust                        # the shipped model
    python bench/bench_robust.py --out runs/robust_new --detector runs/det/detector.pt \
        --pose runs/pose/pose.pt --seg runs/seg/needle_seg.pt --ends runs/ends/needle_ends.pt

The test splits are SEALED: one measurement per shipped model, never used to choose anything.
Choose on the file's val splits with the same bench: ``--role val`` measures those instead (a
candidate checkpoint or setting per ``--out`` folder), e.g.

    python bench/bench_robust.py --role val --data runs/val_data --out runs/val_e27 \
        --pose snapshots/e27/pose.pt
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
from bench_transfer import import_ambf
from benchlib import FLIP_DEG, add_predict_option, predict_options, run

from bopsurg.data_spec import spec_of_file
from bopsurg.evaluation.bootstrap import percentile_interval, resample_weights
from bopsurg.options import read_mapping

SPLITS = Path(__file__).with_name("robust_splits.yaml")
#: The inputs: name -> extra predict arguments.
INPUTS = {"RGB": ["--no-depth"], "RGB-D": []}
#: The errors of the paper's table (errors.csv / summary.json keys).
ERRORS = ("re", "te", "mssd")


def _interval(value: float, ci: list[float] | tuple[float, float] | None, digits: int) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if not ci or any(v is None for v in ci):
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def flip_share(errors: pd.DataFrame, min_visib: float, replicates: int, seed: int = 0) -> dict:
    """Share of the table's matched GT needles (visib_fract >= ``min_visib``) whose RE exceeds
    :data:`~benchlib.FLIP_DEG`, with its 95 % bootstrap interval by image."""
    rows = errors[(errors.visib_fract >= min_visib) & (errors.gt_id >= 0)]
    flipped = (rows.re.to_numpy(float) > FLIP_DEG).astype(float)
    if flipped.size == 0:
        return {"share": float("nan"), "ci95": None}
    units = rows.groupby(["scene_id", "im_id"], sort=True).ngroup().to_numpy(np.int64)
    w = resample_weights(units, replicates, seed)  # (B, N)
    with np.errstate(invalid="ignore"):
        shares = (w @ flipped) / w.sum(axis=1)
    return {"share": float(flipped.mean()), "ci95": list(percentile_interval(shares))}


def table_row(ev: Path, replicates: int) -> dict:
    """One row of the table from an evaluation folder (summary.json with ci95, scores.json,
    errors.csv)."""
    summary = json.loads((ev / "summary.json").read_text())
    scores = json.loads((ev / "scores.json").read_text())
    ci = summary.get("ci95", {}).get("table", {})
    row: dict = {
        k: {"median": summary["table"][k]["median"], "ci95": ci.get(k, {}).get("median")}
        for k in ERRORS
    }
    key = "bop19_average_recall_mssd"
    row["ar_mssd"] = {"value": scores.get(key), "ci95": scores.get("ci95", {}).get(key)}
    errors = pd.read_csv(ev / "errors.csv")
    row["flip"] = flip_share(errors, float(summary["min_visib"]), replicates)
    row["n"] = int(summary["gt_instances"])
    row["found"] = int(summary["with_estimate"])
    return row


def format_table(rows: dict[str, dict[str, dict]]) -> str:
    """The table: one line per (data, input), values with their 95 % intervals."""
    head = ("data", "input", "N found/all", "RE [deg]", "TE [mm]", "MSSD [mm]", "AR_MSSD",
            "RE > 90°")  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for data, by_input in rows.items():
        for name, r in by_input.items():
            flip = r["flip"]
            flip_ci = [100 * v for v in flip["ci95"]] if flip["ci95"] else None
            cells = [
                data, name, f"{r['found']}/{r['n']}",
                *(_interval(r[k]["median"], r[k]["ci95"], 2) for k in ERRORS),
                _interval(r["ar_mssd"]["value"], r["ar_mssd"]["ci95"], 3),
                _interval(100 * flip["share"], flip_ci, 1) + " %",
            ]  # fmt: skip
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def predict_and_eval(
    data: Path, split: str, out: Path, key: str, argv: list[str], args: argparse.Namespace
) -> Path:
    """``bopsurg predict`` then ``bopsurg eval --bootstrap``, each skipped when its output
    exists already; returns the evaluation folder."""
    results, ev = out / f"results_{key}.csv", out / f"eval_{key}"
    if not results.is_file():
        run(["predict", str(data), "--split", split, "--out", str(results), "--device",
             args.device, "--no-progress", *argv], quiet=True)  # fmt: skip
    summary = ev / "summary.json"
    if not (summary.is_file() and "ci95" in json.loads(summary.read_text())):
        run(["eval", str(data), str(results), "--split", split, "--out", str(ev), "--task",
             "bop19", "--renderer", "none", "--bootstrap", str(args.bootstrap),
             "--no-progress"], quiet=True)  # fmt: skip
    return ev


def model_argv(args: argparse.Namespace) -> list[str]:
    """``bopsurg predict`` arguments naming the model (default: the shipped weights)."""
    argv = predict_options(args.predict_option)
    argv += ["--detector", args.detector] if args.detector else []
    argv += ["--pose", args.pose] if args.pose else []
    argv += ["--option", f"refine.segmenter={args.seg}"] if args.seg else []
    argv += ["--option", f"ends.classifier={args.ends}"] if args.ends else []
    return [*(["--config", args.config] if args.config else []), *argv]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True, help="work folder (kept: resumes)")
    ap.add_argument("--splits", type=Path, default=SPLITS, help="the file of splits")
    ap.add_argument("--workers", type=int, default=2, help="generate's worker processes")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--detector", help="detector checkpoint (default: shipped)")
    ap.add_argument("--pose", help="pose head checkpoint (default: shipped)")
    ap.add_argument("--seg", help="needle segmenter checkpoint (default: shipped)")
    ap.add_argument("--ends", help="end classifier checkpoint (default: shipped)")
    ap.add_argument("--config", help="bopsurg predict --config FILE")
    add_predict_option(ap, "ends.margin=3")
    ap.add_argument("--bootstrap", type=int, default=1000, help="bootstrap replicates")
    ap.add_argument(
        "--role", choices=("test", "val"), default="test",
        help="measure the file's sealed test splits (default) or its val splits, to choose on",
    )  # fmt: skip
    ap.add_argument(
        "--only", help="these splits of the --role only (comma-separated; two processes "
        "may measure two splits into one --out at once)",
    )  # fmt: skip
    ap.add_argument("--ambf", type=Path, help="also the AMBF pipeline's frames (a final look)")
    ap.add_argument("--json", type=Path, help="write the table's numbers here")
    ap.add_argument(
        "--data", type=Path,
        help="where the splits' dataset roots and episodes are made (default: --out); one "
        "folder shared by the candidates measured on the same splits",
    )  # fmt: skip
    args = ap.parse_args()
    if args.ambf and args.role == "val":
        ap.error("--ambf is a final look, not a choice: measure it with --role test only")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    made: Path = args.data or out
    spec = spec_of_file(read_mapping(args.splits), args.splits)
    argv = model_argv(args)
    rows: dict[str, dict[str, dict]] = {}
    measured = spec.val if args.role == "val" else spec.test
    names = args.only.split(",") if args.only else measured
    for name in names:
        if name not in measured:
            raise SystemExit(f"{args.splits}: {name!r} is not one of its {args.role} splits")
        data = made / f"data_{name}"
        run(["data", str(args.splits), "--root", str(data), "--only", name, "--bags",
             str(made / "bags"), "--workers", str(args.workers), "--no-progress"])  # fmt: skip
        label = f"{name} (--domain {spec.splits[name].domain})"
        rows[label] = {
            i: table_row(predict_and_eval(data, name, out, f"{name}_{i}", [*argv, *extra], args),
                         args.bootstrap)
            for i, extra in INPUTS.items()
        }  # fmt: skip
    if args.ambf:
        data = out / "ambf" / "data"
        if not data.is_dir():
            import_ambf(args.ambf, args.ambf / "Needle.ply", data)
        rows["AMBF frames (final look)"] = {
            i: table_row(predict_and_eval(data, "test", out, f"ambf_{i}", [*argv, *extra], args),
                         args.bootstrap)
            for i, extra in INPUTS.items()
        }  # fmt: skip
    print(f"\nmodel: {' '.join(argv) or 'the shipped weights'}\n")
    print(format_table(rows))
    if args.json:
        args.json.write_text(json.dumps({"model": argv, "rows": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
