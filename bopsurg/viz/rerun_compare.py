"""Log a comparison of evaluations (``bopsurg compare --rerun``) to a rerun recording.

Layout of the recording (entity paths; ``{key}`` is an evaluation's folder name reduced to
``[A-Za-z0-9_-]``, :attr:`bopsurg.viz.evals.EvalFolder.key`; the first evaluation is the
baseline; ``frame`` is the sequence timeline shared by all evaluations, one step per image
with an estimate of any of them or a GT instance of the paper's table, in
``(scene_id, im_id)`` order; ``eval --rerun`` also counts images whose GT instances are all
below ``--min-visib``, so the two recordings may number frames differently:
``frame_info`` and the reports give the ids):

- ``metrics/{metric}/{key}``: per-frame errors of each evaluation (RE deg, TE mm, MSSD mm,
  MSPD px: the metrics with ``in_rerun``, :mod:`bopsurg.metrics.registry`), one series per
  evaluation in one plot per metric, named by the evaluation; the per-frame value is the
  largest over the frame's matched estimates, as in ``eval --rerun``
  (:func:`bopsurg.viz.rerun_log.frame_table`).
- ``diff/{metric}/{key}``: per frame, the error of evaluation ``key`` minus the baseline's
  (where both matched an estimate): above 0, ``key`` is worse on that frame.
- ``diff/regressions/{key}``: markers at the frames of the worst regressions of ``key``
  (value: the rank, 1 = worst), so they can be found on the timeline.
- ``frame_info/{scene_id,im_id}``: the ids of each frame.
- ``differences/{key}/{scores,table}``: forest plots (2D) of the paired differences (``key``
  minus baseline) with their 95 % bootstrap intervals: ``scores`` the numbers on a 0-1 scale
  (BOP19 ARs, BOP24/25 and COCO scores, recalls, AUCs), ``table`` the paper's table (RE deg,
  TE / MSSD mm); a point per number (blue when its interval excludes 0, grey otherwise,
  labelled with the number, the difference, the interval and the p-value), its interval as
  a segment, and the zero line.
- ``report/differences``: every compared number (both values, difference, interval, p) as
  a markdown table; ``report/regressions``: the worst regressions of each evaluation (largest
  increase of the per-frame MSSD over the baseline's; a frame the baseline matched and the
  other did not comes first).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from bopsurg.metrics.registry import rerun_metrics
from bopsurg.viz.rerun_log import _import_rerun, _send, frame_table

if TYPE_CHECKING:
    from bopsurg.evaluation.bootstrap import Comparison
    from bopsurg.viz.evals import EvalFolder

log = logging.getLogger(__name__)

_KEY = ["scene_id", "im_id"]
#: Forest-plot point colours (RGB): interval excluding 0, including it.
SIGNIFICANT_COLOR = (31, 119, 180)
NOT_SIGNIFICANT_COLOR = (150, 150, 150)
#: Series colours of the evaluations (matplotlib's C0, C1, ...).
SERIES_COLORS = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
]


def comparison_frames(folders: Sequence[EvalFolder]) -> pd.DataFrame:
    """The per-frame errors of every evaluation on one shared ``frame`` numbering.

    Args:
        folders: The compared evaluations (baseline first).

    Returns:
        Columns ``frame`` (0..n-1), ``scene_id``, ``im_id``, then for each evaluation and each
        metric of :func:`~bopsurg.metrics.registry.rerun_metrics` present in its errors.csv
        ``{metric}/{key}`` (RE deg, TE / MSSD mm, MSPD px; the largest over the frame's
        matched estimates, NaN when none is matched). Frames: every ``(scene_id, im_id)``
        with an estimate of any evaluation or a GT instance of a table, sorted.
    """
    parts = [f.errors[_KEY] for f in folders]
    parts += [f.table_rows[_KEY] for f in folders if f.table_rows is not None]
    ids = pd.concat(parts).drop_duplicates().astype(np.int64)
    ids = ids.sort_values(_KEY).reset_index(drop=True)
    out = ids.copy()
    out.insert(0, "frame", np.arange(len(out), dtype=np.int64))
    names = [m.name for m in rerun_metrics()]
    for f in folders:
        per = frame_table(f.errors, ids)  # ids as the GT rows: the same frames for everyone
        cols = [n for n in names if n in per]
        per = per[[*_KEY, *cols]].rename(columns={n: f"{n}/{f.key}" for n in cols})
        out = out.merge(per, on=_KEY, how="left")
    return out


def worst_regressions(
    frames: pd.DataFrame, base_key: str, other_key: str, metric: str = "mssd", n: int = 20
) -> pd.DataFrame:
    """The frames where an evaluation is most worse than the baseline.

    Args:
        frames: :func:`comparison_frames`.
        base_key, other_key: The two evaluations' keys.
        metric: The per-frame error compared (``mssd``: mm).
        n: At most this many frames.

    Returns:
        Columns ``frame``, ``scene_id``, ``im_id``, ``base``, ``other`` and ``diff``
        (other - base; +inf where the baseline matched an estimate and the other did not),
        only frames with ``diff > 0``, the largest first.
    """
    base = frames[f"{metric}/{base_key}"].to_numpy(float)
    other = frames[f"{metric}/{other_key}"].to_numpy(float)
    diff = np.where(np.isfinite(base) & np.isnan(other), np.inf, other - base)
    table = frames[["frame", *_KEY]].assign(base=base, other=other, diff=diff)
    table = table[np.nan_to_num(diff, nan=-1.0) > 0]
    return table.sort_values("diff", ascending=False, kind="stable").head(max(0, n))


@dataclass(frozen=True)
class ForestRow:
    """One number of a comparison in a forest plot.

    Attributes:
        key: The number's name (``bop24_mAP``, ``re_median``, ...).
        diff: Other minus baseline (the number's unit: deg, mm or a 0-1 score).
        ci: Its 95 % paired bootstrap interval.
        p_value: Two-sided paired bootstrap p-value.
    """

    key: str
    diff: float
    ci: tuple[float, float]
    p_value: float

    @property
    def significant(self) -> bool:
        """The interval excludes 0."""
        return self.ci[0] > 0 or self.ci[1] < 0


def _group(key: str) -> str:
    table = key.split("_")[-1] in ("mean", "std", "median") and not key.startswith("bop")
    return "table" if table else "scores"


def forest_rows(comparison: Mapping[str, Comparison]) -> dict[str, list[ForestRow]]:
    """The compared numbers by forest plot: ``scores`` (0-1 scale) and ``table`` (the paper's
    table: RE deg, TE / MSSD mm), in the comparison's order; numbers without a finite
    difference are left out."""
    out: dict[str, list[ForestRow]] = {"scores": [], "table": []}
    for key, c in comparison.items():
        if np.isfinite(c.diff):
            ci = (float(c.ci[0]), float(c.ci[1]))
            out[_group(key)].append(ForestRow(key, float(c.diff), ci, float(c.p_value)))
    return {g: rows for g, rows in out.items() if rows}


def forest_geometry(rows: Sequence[ForestRow]) -> dict[str, NDArray[np.float64]]:
    """Where a forest plot's elements go in its 2D view (x: the difference; y: the row, down).

    Returns:
        ``points`` (R, 2) the differences, ``intervals`` (R, 2, 2) the interval segments,
        ``zero`` (2, 2) the zero line. Rows are spaced so the plot is wider than tall
        whatever the differences' unit (0.8 × the x span for all rows together).
    """
    lo = min(0.0, *(r.ci[0] for r in rows if np.isfinite(r.ci[0])), *(r.diff for r in rows))
    hi = max(0.0, *(r.ci[1] for r in rows if np.isfinite(r.ci[1])), *(r.diff for r in rows))
    span = hi - lo if hi > lo else 1.0
    step = 0.8 * span / max(len(rows), 1)
    y = np.arange(len(rows), dtype=np.float64) * step
    x = np.array([r.diff for r in rows], np.float64)
    ci = np.array([r.ci for r in rows], np.float64).reshape(-1, 2)
    ci = np.where(np.isfinite(ci), ci, x[:, None])
    intervals = np.stack([np.stack([ci[:, 0], y], 1), np.stack([ci[:, 1], y], 1)], 1)
    zero = np.array([[0.0, -step], [0.0, y[-1] + step if len(y) else step]], np.float64)
    return {"points": np.stack([x, y], 1), "intervals": intervals, "zero": zero}


def _p_text(p: float, replicates: int | None) -> str:
    if p == 0 and replicates:
        return f"<{1 / replicates:.2g}"
    return f"{p:.3f}"


def _blueprint(rrb: Any, folders: Sequence[EvalFolder], groups: Sequence[str]) -> Any:
    names = [m.name for m in rerun_metrics()]
    base, others = folders[0], folders[1:]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Tabs(
                    *(
                        rrb.TimeSeriesView(name=f"{n.upper()} per frame", origin=f"metrics/{n}")
                        for n in names
                    )
                ),
                rrb.Tabs(
                    *(
                        rrb.TimeSeriesView(
                            name=f"{n.upper()} minus {base.label}", origin=f"diff/{n}"
                        )
                        for n in names
                    ),
                    rrb.TimeSeriesView(name="regressions", origin="diff/regressions"),
                ),
            ),
            rrb.Vertical(
                rrb.Tabs(
                    *(
                        rrb.Spatial2DView(
                            name=f"{f.label} - {base.label}: {g}",
                            origin=f"differences/{f.key}/{g}",
                        )
                        for f in others
                        for g in groups
                    )
                ),
                rrb.Tabs(
                    rrb.TextDocumentView(name="worst regressions", origin="report/regressions"),
                    rrb.TextDocumentView(name="differences", origin="report/differences"),
                ),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def log_comparison(
    folders: Sequence[EvalFolder],
    comparisons: Sequence[Mapping[str, Comparison]],
    path: str | Path,
    *,
    worst: int = 20,
    replicates: int | None = None,
) -> Path:
    """Write a comparison as a rerun recording, headless (no viewer is started).

    Args:
        folders: The compared evaluations, baseline first
            (:func:`bopsurg.viz.evals.load_eval_folders`).
        comparisons: For each evaluation after the baseline, its paired comparison with the
            baseline (``bopsurg compare``: number →
            :class:`~bopsurg.evaluation.bootstrap.Comparison`).
        path: The ``.rrd`` file to write (parent folders are created).
        worst: Length of each evaluation's list of worst regressions (per-frame MSSD, mm).
        replicates: The bootstrap replicates (a p-value of 0 is shown as ``<1/replicates``).

    Returns:
        The written path. Open it with ``rerun FILE.rrd``.

    Raises:
        BopsurgError: rerun-sdk is not installed.
    """
    if len(comparisons) != len(folders) - 1:
        raise ValueError("one comparison per evaluation after the baseline")
    rr = _import_rerun()
    import rerun.blueprint as rrb

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = comparison_frames(folders)
    forests = [forest_rows(c) for c in comparisons]
    groups = [g for g in ("scores", "table") if any(g in f for f in forests)]
    rec = rr.RecordingStream("bopsurg_compare", recording_id=None)
    rec.save(path, default_blueprint=_blueprint(rrb, folders, groups))
    try:
        _log_series(rr, rec, frames, folders, worst)
        for other, forest in zip(folders[1:], forests, strict=True):
            for group, rows in forest.items():
                _log_forest(rr, rec, f"differences/{other.key}/{group}", rows, replicates)
        _log_reports(rr, rec, frames, folders, comparisons, worst, replicates)
        log.info("rerun: %d evaluations, %d frames -> %s", len(folders), len(frames), path)
    finally:
        rec.flush()
        rec.disconnect()
    return path


def _log_series(
    rr: Any, rec: Any, frames: pd.DataFrame, folders: Sequence[EvalFolder], worst: int
) -> None:
    frame = frames["frame"].to_numpy(np.int64)
    base = folders[0]
    for i, f in enumerate(folders):
        color = SERIES_COLORS[i % len(SERIES_COLORS)]
        for m in rerun_metrics():
            col = f"{m.name}/{f.key}"
            if col not in frames:
                continue
            entity = f"metrics/{m.name}/{f.key}"
            rec.log(entity, rr.SeriesLines(names=f.label, colors=[color]), static=True)
            _send(rr, rec, entity, frame, frames[col].to_numpy(float))
            base_col = f"{m.name}/{base.key}"
            if i == 0 or base_col not in frames:
                continue
            entity = f"diff/{m.name}/{f.key}"
            name = f"{f.label} - {base.label} [{m.unit}]"
            rec.log(entity, rr.SeriesLines(names=name, colors=[color]), static=True)
            diff = frames[col].to_numpy(float) - frames[base_col].to_numpy(float)
            _send(rr, rec, entity, frame, diff)
        if i == 0 or "mssd/" + f.key not in frames:
            continue
        top = worst_regressions(frames, base.key, f.key, "mssd", worst)
        if len(top):
            entity = f"diff/regressions/{f.key}"
            order = np.argsort(top["frame"].to_numpy())
            rec.log(
                entity,
                rr.SeriesPoints(
                    names=f"{f.label}: rank", colors=[color], markers="cross", marker_sizes=6.0
                ),
                static=True,
            )
            _send(
                rr,
                rec,
                entity,
                top["frame"].to_numpy(np.int64)[order],
                np.arange(1, len(top) + 1, dtype=float)[order],
            )
    for name in _KEY:
        _send(rr, rec, f"frame_info/{name}", frame, frames[name].to_numpy(float))


def _log_forest(
    rr: Any, rec: Any, entity: str, rows: Sequence[ForestRow], replicates: int | None
) -> None:
    geo = forest_geometry(rows)
    colors = [SIGNIFICANT_COLOR if r.significant else NOT_SIGNIFICANT_COLOR for r in rows]
    labels = [
        f"{r.key}: {r.diff:+.4g} [{r.ci[0]:+.4g}, {r.ci[1]:+.4g}] "
        f"p {_p_text(r.p_value, replicates)}"
        for r in rows
    ]
    rec.log(f"{entity}/zero", rr.LineStrips2D([geo["zero"]], colors=[(0, 0, 0)]), static=True)
    rec.log(
        f"{entity}/intervals",
        rr.LineStrips2D(list(geo["intervals"]), colors=colors, radii=rr.Radius.ui_points(1.5)),
        static=True,
    )
    rec.log(
        f"{entity}/points",
        rr.Points2D(
            geo["points"],
            colors=colors,
            labels=labels,
            radii=rr.Radius.ui_points(4.0),
            show_labels=True,
        ),
        static=True,
    )


def _log_reports(
    rr: Any,
    rec: Any,
    frames: pd.DataFrame,
    folders: Sequence[EvalFolder],
    comparisons: Sequence[Mapping[str, Comparison]],
    worst: int,
    replicates: int | None,
) -> None:
    base = folders[0]
    diff_lines = [f"# Paired differences to {base.label} (95 % bootstrap intervals)", ""]
    reg_lines = [
        f"# Worst regressions (per-frame MSSD [mm] minus {base.label}'s)",
        "",
        "Jump there on the `frame` timeline; `diff/regressions` marks them.",
    ]
    for f, comparison in zip(folders[1:], comparisons, strict=True):
        diff_lines += [
            f"## {f.label} - {base.label}",
            "",
            f"| number | {base.label} | {f.label} | diff | 95 % interval | p |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for key, c in comparison.items():
            diff_lines.append(
                f"| {key} | {c.a:.4f} | {c.b:.4f} | {c.diff:+.4f} | "
                f"[{c.ci[0]:+.4f}, {c.ci[1]:+.4f}] | {_p_text(c.p_value, replicates)} |"
            )
        diff_lines.append("")
        reg_lines += ["", f"## {f.label}", ""]
        if "mssd/" + f.key not in frames or "mssd/" + base.key not in frames:
            reg_lines.append("no MSSD per frame")
            continue
        top = worst_regressions(frames, base.key, f.key, "mssd", worst)
        if not len(top):
            reg_lines.append(f"no frame where {f.label} is worse than {base.label}")
            continue
        reg_lines += [
            f"| rank | frame | scene | image | {base.label} | {f.label} | diff |",
            "|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for rank, r in enumerate(top.itertuples(index=False), start=1):
            other = "missed" if np.isnan(r.other) else f"{r.other:.2f}"
            diff = "missed" if np.isinf(r.diff) else f"{r.diff:+.2f}"
            reg_lines.append(
                f"| {rank} | {r.frame} | {r.scene_id} | {r.im_id} | {r.base:.2f} | {other} "
                f"| {diff} |"
            )
    for entity, lines in (("report/differences", diff_lines), ("report/regressions", reg_lines)):
        rec.log(
            entity,
            rr.TextDocument("\n".join(lines), media_type=rr.MediaType.MARKDOWN),
            static=True,
        )
