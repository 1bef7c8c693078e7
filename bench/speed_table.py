"""The README's speed table, measured in one run on this machine, printed as Markdown.

Runs ``bench_metrics.py`` (batched metrics vs the per-pose reference loop; with ``--device``
also the torch backend) and ``bench_eval.py`` (``bopsurg eval`` at scale; with ``--data``,
``--results`` and ``--toolkit`` also against the reference toolkit's scripts), each in its own
process, then prints one table headed by the machine (platform, CPU model, cores).

    python bench/speed_table.py [--poses 1000] [--estimates 100000] [--device cuda]
        [--data demo_out/data --results demo_out/results.csv
         --toolkit ../bop_toolkit --toolkit-python ../bop-venv/bin/python]
        [--predict DATASET --batch-size 8]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench_metrics import machine

HERE = Path(__file__).parent
METRIC_ROWS = {"mssd": "MSSD", "mspd": "MSPD", "add": "ADD", "adi": "ADD-S"}


def bench(script: str, argv: list[str], out: Path) -> Any:
    """Run a bench with ``--json out``; its JSON."""
    cmd = [sys.executable, str(HERE / script), *argv, "--json", str(out)]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())


def metric_rows(res: dict[str, Any], syms: int) -> list[str]:
    rows = []
    for r in res["rows"]:
        name = METRIC_ROWS.get(r["metric"])
        model = f"{r['model']} model, {r['poses']} poses"
        if r["metric"].startswith(("mssd", "mspd")):
            model += f", {syms} symmetries"
        if name and "torch_vs_numpy" not in r:
            rows.append(
                f"| {name}, {model} | {r['bopsurg_ms_per_pose']:.4f} ms/pose "
                f"| {r['reference_ms_per_pose']:.2f} ms/pose | {r['speedup']:.0f}x |"
            )
        elif "torch_vs_numpy" in r:
            rows.append(
                f"| {r['metric']} vs numpy, {model} | "
                f"{r['bopsurg_ms_per_pose']:.5f} ms/pose | numpy {r['numpy_ms_per_pose']:.4f} "
                f"ms/pose | {r['torch_vs_numpy']:.1f}x |"
            )
    return rows


def predict_rows(dataset: str, batch: int, out: Path) -> list[str]:
    """``bopsurg predict``'s ms per image (bench_predict_speed.py), against the networks alone."""
    argv = [dataset, "--batch-size", str(batch), "--images", "48"]
    res = bench("bench_predict_speed.py", argv, out)
    ms = res["ms_per_image"][str(batch)]
    base = ms["networks alone"]
    return [
        f"| `bopsurg predict`, {name}, batch {batch}, 640x480 | {v:.0f} ms/image | "
        f"networks alone {base:.0f} ms/image | {v / base:.2f}x the networks |"
        for name, v in ms.items()
        if name != "networks alone"
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--poses", type=int, default=1000)
    ap.add_argument("--vertices", type=int, default=5000)
    ap.add_argument("--symmetries", type=int, default=315)
    ap.add_argument("--estimates", type=int, default=100_000, help="bench_eval at scale")
    ap.add_argument("--device", choices=("cpu", "cuda", "auto"), help="also the torch backend")
    ap.add_argument("--data", help="dataset for the comparison with the reference scripts")
    ap.add_argument("--results", help="its results CSV")
    ap.add_argument("--toolkit", help="thodan/bop_toolkit checkout")
    ap.add_argument("--toolkit-python", default="python")
    ap.add_argument("--predict", metavar="DATASET", help="also bopsurg predict per image on it")
    ap.add_argument("--batch-size", type=int, default=8, help="with --predict")
    args = ap.parse_args()
    size = ["--vertices", str(args.vertices), "--symmetries", str(args.symmetries)]
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        timeline = ""
        rows = metric_rows(bench("bench_metrics.py", ["--poses", str(args.poses), *size],
                                 t / "m.json"), args.symmetries)  # fmt: skip
        if args.device:
            dev = ["--device", args.device, "--poses", str(10 * args.poses), *size]
            gpu = bench("bench_metrics.py", dev, t / "g.json")
            rows += [r for r in metric_rows(gpu, args.symmetries) if " vs numpy" in r]
        ev = bench("bench_eval.py", ["--estimates", str(args.estimates), "--out", tmp],
                   t / "e.json")  # fmt: skip
        rows.append(
            f"| `bopsurg eval`, {ev['estimates']:,} estimates, {ev['vertices']}-vertex needle | "
            f"{ev['evaluate_without_adi_s']:.1f} s without ADD-S, {ev['total_s']:.1f} s with | "
            "| |"
        )
        if args.data and args.results:
            cmp_args = ["--data", args.data, "--results", args.results, "--out", tmp, "--timeline"]
            if args.toolkit:
                cmp_args += ["--toolkit", args.toolkit, "--toolkit-python", args.toolkit_python]
            c = bench("bench_eval.py", cmp_args, t / "c.json")
            ref = f"{c['reference_s']:.1f} s (eval_bop19_pose.py)" if "ratio" in c else ""
            ratio = f"{c['ratio']:.1f}x" if "ratio" in c else ""
            rows.append(
                f"| `bopsurg eval` with VSD, {'/'.join(Path(args.data).parts[-2:])} | "
                f"{c['bopsurg_s']:.2f} s | "
                f"{ref} | {ratio} |"
            )
            timeline = f"VSD of `bopsurg eval` with VSD: {c.get('vsd_timeline', '')}"
        if args.predict:
            rows += predict_rows(args.predict, args.batch_size, t / "p.json")
    print(f"Machine: {machine()}\n")
    print("| workload | bopsurg | reference | ratio |\n|---|---|---|---|")
    print("\n".join(rows))
    if timeline:
        print(f"\n{timeline}")


if __name__ == "__main__":
    main()
