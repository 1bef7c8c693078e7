"""`generate` and `eval` on a real two-node Ray cluster give the local executor's bytes, and a
worker killed mid-run loses nothing.

The cluster (a head and a second node, separate processes) runs inside a network namespace
made by the test with only its loopback interface up, so every connection stays on
127.0.0.1 (this workplace allows no traffic to other addresses). Needs root and iproute2;
skipped otherwise.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import pytest

from bopsurg.bop.dataset import BopDataset
from bopsurg.bop.results import save_results
from bopsurg.cli.main import main
from tests.helpers import estimates_from_gt
from tests.ray_netns import PORT, Cluster, netns_available

pytest.importorskip("ray")
pytest.importorskip("pybullet")


pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(not netns_available(), reason="needs root and ip netns"),
]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(nodes=2)
    yield c
    c.close()


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    path = tmp_path_factory.mktemp("bag") / "a.bag"
    assert main(["record", "--out", str(path), "--seed", "4", "--duration", "4"]) == 0
    return path


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "bopsurg_generate.json"
    }


GEN = ["--replays", "3", "--period", "1.0", "--seed", "9", "--no-progress"]


def test_generate_and_eval_on_ray_equal_local(cluster, bag, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    assert main(["generate", str(bag), "--out", str(local), *GEN]) == 0
    r = cluster.sh(
        f"bopsurg generate {bag} --out {remote} {' '.join(GEN)} "
        f"--executor ray --ray-address 127.0.0.1:{PORT}"
    )
    assert "3 scenes" in r.stdout
    assert _digest(remote) == _digest(local)

    d = BopDataset(local, "test")
    est = estimates_from_gt(d, t_offset_mm=0.5)
    results = tmp_path / "r_needle-test.csv"
    save_results(results, est)
    assert (
        main(
            ["eval", str(local), str(results), "--out", str(tmp_path / "ev_local"), "--no-progress"]
        )
        == 0
    )
    cluster.sh(
        f"bopsurg eval {local} {results} --out {tmp_path / 'ev_ray'} --no-progress "
        f"--executor ray --ray-address 127.0.0.1:{PORT}"
    )
    for name in ("errors.csv", "summary.json", "scores.json"):
        a = (tmp_path / "ev_local" / name).read_text()
        b = (tmp_path / "ev_ray" / name).read_text()
        if name == "summary.json":  # the results path differs only in the metadata
            a, b = a.replace(str(local), "X"), b.replace(str(local), "X")
        assert a == b, name


def test_worker_killed_mid_run_loses_nothing(cluster, bag, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    # enough work per replay that one is surely running when the worker is killed
    args = ["--replays", "4", "--period", "0.25", "--seed", "11", "--no-progress"]
    assert main(["generate", str(bag), "--out", str(local), *args]) == 0
    proc = cluster.sh(
        f"bopsurg generate {bag} --out {remote} {' '.join(args)} "
        f"--executor ray --ray-address 127.0.0.1:{PORT}",
        background=True,
    )
    # Wait until a replay is under way, then kill the worker process running one.
    deadline = time.time() + 120
    while time.time() < deadline and not list(remote.glob("test/*/rgb/*")):
        time.sleep(0.2)
    killed = cluster.kill("ray::_ray_call")
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err.decode()[-2000:]
    assert killed > 0, "no running replay task was found to kill"
    assert _digest(remote) == _digest(local)
