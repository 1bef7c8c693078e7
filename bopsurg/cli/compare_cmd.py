"""``bopsurg compare``: paired bootstrap comparison of evaluations of the same test set."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

from bopsurg.cli.commands import help_of
from bopsurg.cli.inputs import add_bootstrap_args
from bopsurg.errors import BopsurgError

if TYPE_CHECKING:
    from bopsurg.cli.commands import Subparsers
    from bopsurg.evaluation.bootstrap import Comparison, DetectionSamples
    from bopsurg.viz.evals import EvalFolder

    #: One compared evaluation: its folder and the comparison of each number with the base.
    Compared = tuple[Path, dict[str, Comparison]]

HELP = help_of("compare")

DESCRIPTION = """\
Compare two or more evaluations of the same test set (folders written by 'bopsurg eval').
The first is the baseline; each other one is compared with it on
the same bootstrap replicates (paired: the same images drawn for both methods), which is
what separates a real difference from the luck of the test set.

For every number of the paper's table (mean, std, median of RE / TE / MSSD), the recalls
at absolute thresholds, ADD / ADD-S AUC, the BOP19 ARs and, when evaluated, every
BOP24/BOP25 score and every COCO AP / AR (evaluations of the detector's COCO JSON):
both values, the difference (other - baseline), its 95 % interval, and the two-sided
paired bootstrap p-value of "no difference". An interval that excludes
0 (p < 0.05) is a difference the test set supports.

Writes into --out: compare.json, and compare.png (needs matplotlib: bopsurg[figures]).

--figures (needs --out and matplotlib) also writes OUT/figures/, PNG + PDF, every evaluation
drawn on the same axes in its own colour: fig4_error_histograms (RE / TE / MSSD with each
one's median), recall_curves (one curve per evaluation and metric), bop24_pr_curves (the
evaluations with the bop24 task) and, once for the shared test set, fig2_gt_distributions
(GT distance and visibility, from the dataset named in summary.json; skipped when that
dataset is no longer there, refused when two evaluations name datasets with different GT).

--rerun [FILE.rrd] (default OUT/compare.rrd) writes a rerun recording: the per-frame errors
of every evaluation on one 'frame' timeline (metrics/<metric>/<eval>), each one's per-frame
difference to the baseline (diff/<metric>/<eval>: above 0 it is worse there) with its worst
regressions marked (diff/regressions/<eval>) and listed (report/regressions), and forest
plots of the paired differences with their intervals (differences/<eval>/{scores,table}).
Put a bare --rerun after the folders (else it takes the first folder as its file).

--figures and --rerun need evaluations of pose results (errors.csv) of the same test set.

Example:
  bopsurg eval DATA a.csv --out eval_a && bopsurg eval DATA b.csv --out eval_b
  bopsurg compare eval_a eval_b --out cmp --figures --rerun
  rerun cmp/compare.rrd
"""

#: --rerun without a file name: OUT/compare.rrd.
_DEFAULT_RRD = "compare.rrd"


def register(sub: Subparsers) -> None:
    """Add the ``compare`` subcommand."""
    p = sub.add_parser(
        "compare", help=HELP, description=DESCRIPTION, formatter_class=argparse.RawTextHelpFormatter
    )
    p.add_argument("evals", nargs="+", metavar="EVAL_DIR", help="folders of 'bopsurg eval'")
    p.add_argument("--out", default=None, help="folder for compare.json and compare.png")
    p.add_argument(
        "--figures",
        action="store_true",
        help="also write OUT/figures/: Fig. 2, Fig. 4, recall and BOP24 PR curves of every "
        "evaluation overlaid, PNG + PDF (needs --out and matplotlib)",
    )
    p.add_argument(
        "--rerun",
        metavar="FILE.rrd",
        nargs="?",
        const=_DEFAULT_RRD,
        default=None,
        help="also write a rerun recording of the comparison (default file: OUT/compare.rrd; "
        "needs bopsurg[rerun])",
    )
    add_bootstrap_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Compare every evaluation with the first one; print the table, write the files."""
    from bopsurg.atomic import write_text
    from bopsurg.evaluation.bootstrap import json_strict

    if args.rerun is not None:
        _rrd_path(args)  # first: 'compare --rerun A B' took A as the file
    if len(args.evals) < 2:
        raise BopsurgError("compare needs at least two evaluation folders")
    if args.bootstrap < 1:
        raise BopsurgError("--bootstrap: compare needs at least 1 replicate")
    folders = _load_for_outputs(args)  # before the bootstrap: a bad input fails first
    base_dir = Path(args.evals[0])
    report: dict[str, object] = {
        "baseline": str(base_dir),
        "bootstrap": {"replicates": args.bootstrap, "unit": args.ci_unit, "seed": args.seed},
        "comparisons": {},
    }
    rows: list[Compared] = []
    for other_dir in map(Path, args.evals[1:]):
        try:
            res = compare_pair(base_dir, other_dir, args.bootstrap, args.seed, args.ci_unit)
        except BopsurgError as err:
            raise BopsurgError(f"{base_dir} vs {other_dir}: {err}") from None
        report["comparisons"][str(other_dir)] = {k: asdict(c) for k, c in res.items()}  # type: ignore[index]
        rows.append((other_dir, res))
    print(_table(base_dir, rows, args.bootstrap))
    if args.out is not None:
        out = Path(args.out)
        write_text(out / "compare.json", json.dumps(json_strict(report), indent=2) + "\n")
        written = [out / "compare.json"]
        png = _plot(base_dir, rows, out / "compare.png")
        if png is not None:
            written.append(png)
        print("\nwrote " + ", ".join(str(p) for p in written))
    if folders is not None and args.figures:
        from bopsurg.viz.evals import comparison_gt
        from bopsurg.viz.figures import write_comparison_figures

        figures_dir = Path(args.out) / "figures"
        paths = write_comparison_figures(folders, figures_dir, comparison_gt(folders))
        print(f"wrote {len(paths)} figure files into {figures_dir}")
    if folders is not None and args.rerun is not None:
        from bopsurg.viz.rerun_compare import log_comparison

        rrd = log_comparison(
            folders, [res for _, res in rows], _rrd_path(args), replicates=args.bootstrap
        )
        print(f"wrote {rrd}; open it with: rerun {rrd}")
    return 0


def _rrd_path(args: argparse.Namespace) -> Path:
    """--rerun's file: as given, or OUT/compare.rrd for a bare --rerun."""
    if args.rerun == _DEFAULT_RRD:
        if args.out is None:
            raise BopsurgError("--rerun without a file name writes OUT/compare.rrd: give --out")
        return Path(args.out) / _DEFAULT_RRD
    if Path(args.rerun).is_dir():  # e.g. 'compare --rerun eval_a eval_b': a folder taken
        raise BopsurgError(
            f"--rerun {args.rerun}: a folder; give the .rrd file to write, or put --rerun "
            "after the evaluation folders"
        )
    return Path(args.rerun)


def _load_for_outputs(args: argparse.Namespace) -> list[EvalFolder] | None:
    """With --figures or --rerun: check their options and dependencies, then read the
    evaluation folders (errors.csv, same test set); None without either."""
    if not args.figures and args.rerun is None:
        return None
    if args.figures:
        if args.out is None:
            raise BopsurgError("--figures writes OUT/figures/: give --out")
        from bopsurg.viz.figures import _pyplot

        _pyplot()  # one line naming bopsurg[figures] when matplotlib is missing
    if args.rerun is not None:
        _rrd_path(args)
        from bopsurg.viz.rerun_log import _import_rerun

        _import_rerun()
    from bopsurg.viz.evals import load_eval_folders

    return load_eval_folders([Path(p) for p in args.evals])


def compare_pair(
    base_dir: Path, other_dir: Path, replicates: int, seed: int, unit: str
) -> dict[str, Comparison]:
    """Paired comparisons of every number both evaluation folders can be resampled for: the
    paper's table, recalls and AUCs (pose results), BOP19 ARs, BOP24/BOP25 and COCO scores.

    Raises:
        BopsurgError: Nothing in common, or not the same targets.
    """
    from bopsurg.evaluation.bootstrap import (
        BOP19_SAMPLES_FILENAME,
        compare_bop19,
        compare_samples,
        load_bop19_counts,
    )
    from bopsurg.evaluation.coco_bootstrap import COCO_SAMPLES_FILENAME, CocoSamples, compare_coco
    from bopsurg.evaluation.summary_ci import (
        TABLE_SAMPLES_FILENAME,
        compare_tables,
        load_table_rows,
    )

    def both(name: str) -> bool:
        return (base_dir / name).exists() and (other_dir / name).exists()

    has_table = [(d / TABLE_SAMPLES_FILENAME).exists() for d in (base_dir, other_dir)]
    if any(has_table) and not all(has_table):
        missing = (other_dir if has_table[0] else base_dir) / TABLE_SAMPLES_FILENAME
        raise BopsurgError(f"{missing}: missing (evaluate the pose results with this bopsurg)")
    for d in (base_dir, other_dir):
        if not (d / "scores.json").exists():
            raise BopsurgError(f"{d}: not a folder written by 'bopsurg eval' (no scores.json)")
    res: dict[str, Comparison] = {}
    if both(TABLE_SAMPLES_FILENAME):
        base_table = load_table_rows(base_dir / TABLE_SAMPLES_FILENAME)
        other_table = load_table_rows(other_dir / TABLE_SAMPLES_FILENAME)
        res |= compare_tables(base_table, other_table, replicates, seed, unit)
    base, other = _bop24_samples(base_dir), _bop24_samples(other_dir)
    if base is not None and other is not None:
        res |= compare_samples(base, other, replicates, seed, unit)
    base19 = load_bop19_counts(base_dir / BOP19_SAMPLES_FILENAME)
    other19 = load_bop19_counts(other_dir / BOP19_SAMPLES_FILENAME)
    if base19 and other19:
        res |= compare_bop19(base19, other19, replicates, seed, unit)
    if both(COCO_SAMPLES_FILENAME):
        coco_a = CocoSamples.load(base_dir / COCO_SAMPLES_FILENAME)
        coco_b = CocoSamples.load(other_dir / COCO_SAMPLES_FILENAME)
        res |= compare_coco(coco_a, coco_b, replicates, seed, unit)
    if not res:
        raise BopsurgError(
            "nothing to compare: the evaluations share no task (pose results vs COCO JSON?)"
        )
    return res


def _bop24_samples(eval_dir: Path) -> DetectionSamples | None:
    """The BOP24 samples of an evaluation, None when it ran without the bop24 task."""
    from bopsurg.evaluation.bootstrap import SAMPLES_FILENAME, DetectionSamples

    path = eval_dir / SAMPLES_FILENAME
    return DetectionSamples.load(path) if path.exists() else None


def _table(base_dir: Path, rows: list[Compared], replicates: int) -> str:
    """The printed comparison (a p-value of 0 is below the bootstrap's resolution)."""
    lines = []
    for other_dir, res in rows:
        w = max([20, *(len(k) + 2 for k in res)])
        lines += [
            f"{other_dir} - {base_dir}:",
            f"  {'score':<{w}}{'baseline':>10}{'other':>10}{'diff':>10}"
            f"{'95 % interval':>22}{'p':>8}",
        ]
        for key, c in res.items():
            ci = f"[{c.ci[0]:+.4f}, {c.ci[1]:+.4f}]"
            p = f"<{1 / replicates:.2g}" if c.p_value == 0 else f"{c.p_value:.3f}"
            lines.append(f"  {key:<{w}}{c.a:>10.4f}{c.b:>10.4f}{c.diff:>+10.4f}{ci:>22}{p:>8}")
    return "\n".join(lines)


def _plot(base_dir: Path, rows: list[Compared], path: Path) -> Path | None:
    """Forest plot of the differences with their intervals (None without matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("compare.png skipped: needs matplotlib (pip install 'bopsurg[figures]')")
        return None
    # Scores on a common 0-1 scale (the table's deg / mm statistics are in the JSON).
    keys = [k for k in rows[0][1] if k.startswith(("bop2", "recall_")) or k.endswith("_auc")]
    fig, ax = plt.subplots(figsize=(6.4, 0.5 + 0.45 * len(keys) * len(rows)))
    y = 0
    ticks, labels = [], []
    for other_dir, res in rows:
        for key in keys:
            c = res[key]
            ax.errorbar(c.diff, y, xerr=[[c.diff - c.ci[0]], [c.ci[1] - c.diff]], fmt="o",
                        color="C0" if c.ci[0] > 0 or c.ci[1] < 0 else "C7", capsize=3)  # fmt: skip
            ticks.append(y)
            labels.append(f"{key} ({other_dir.name})" if len(rows) > 1 else key)
            y -= 1
    ax.axvline(0.0, color="k", lw=0.8)
    ax.set_yticks(ticks, labels)
    ax.set_xlabel(f"difference to {base_dir.name} (95 % paired bootstrap interval)")
    fig.tight_layout()
    from bopsurg.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=150)
    plt.close(fig)
    return path
