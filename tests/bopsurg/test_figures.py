"""Figures of an evaluation: which rows they draw, and the files eval --figures writes."""

from __future__ import annotations

import pandas as pd
import pytest

from bopsurg.cli.main import main
from bopsurg.viz.figures import matched_errors
from tests.bopsurg.evaluation.test_bop24 import _hand_dataset


def test_matched_errors_keep_matched_visible_instances():
    errors = pd.DataFrame(
        {"gt_id": [0, -1, 1, 2], "visib_fract": [0.9, 0.9, 0.2, 0.3], "re": [1.0, 2, 3, 4]}
    )
    assert matched_errors(errors, 0.3)["re"].tolist() == [1.0, 4.0]


def test_eval_figures_writes_png_and_pdf(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    _hand_dataset(tmp_path)
    out = tmp_path / "out"
    args = ["eval", str(tmp_path), str(tmp_path / "r.csv"), "--out", str(out), "--figures"]
    assert main([*args, "--bootstrap", "0"]) == 0
    assert "wrote 8 figure files" in capsys.readouterr().out
    names = ("fig2_gt_distributions", "fig4_error_histograms", "recall_curves", "bop24_pr_curves")
    for name in names:
        assert (out / "figures" / f"{name}.png").read_bytes()[:4] == b"\x89PNG"
        assert (out / "figures" / f"{name}.pdf").read_bytes()[:5] == b"%PDF-"
    assert main([*args, "--task", "bop19"]) == 0  # no BOP24 curves without the task
    assert "wrote 6 figure files" in capsys.readouterr().out
