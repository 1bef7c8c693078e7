"""A local multi-node Ray cluster inside a network namespace (tests and bench).

Every process of the cluster, and the driver run through :meth:`Cluster.sh`, lives in a
namespace whose only interface is loopback, so all traffic stays on 127.0.0.1. Needs root
and iproute2 (``ip netns``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

BIN = Path(sys.executable).parent
PORT = 6391


def netns_available() -> bool:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return False
    name = f"bopsurg-probe-{uuid.uuid4().hex[:6]}"
    ok = subprocess.run(["ip", "netns", "add", name], capture_output=True).returncode == 0
    if ok:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return ok


class Cluster:
    """A head and a worker node (1 CPU each) in a fresh network namespace."""

    def __init__(self, nodes: int = 2, cpus_per_node: int = 1) -> None:
        self.ns = f"bopsurg-ray-{uuid.uuid4().hex[:6]}"
        self.tmp = Path("/tmp") / f"rb{uuid.uuid4().hex[:6]}"  # short: socket path limits
        self.env = {
            **os.environ,
            "PATH": f"{BIN}:{os.environ['PATH']}",
            "RAY_USAGE_STATS_ENABLED": "0",
        }
        subprocess.run(["ip", "netns", "add", self.ns], check=True)
        self.sh("ip link set lo up")
        common = f"--num-cpus={cpus_per_node} --disable-usage-stats --node-ip-address=127.0.0.1"
        head = f"--head --port={PORT} --include-dashboard=false --temp-dir={self.tmp}"
        self.sh(f"ray start {head} {common}")
        for _ in range(nodes - 1):
            self.sh(f"ray start --address=127.0.0.1:{PORT} {common}")

    def sh(self, cmd: str, *, check: bool = True, background: bool = False):
        args = ["ip", "netns", "exec", self.ns, "bash", "-c", cmd]
        if background:
            return subprocess.Popen(
                args, env=self.env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
            )
        return subprocess.run(args, env=self.env, check=check, capture_output=True, text=True)

    def kill(self, pattern: str) -> int:
        """SIGKILL this namespace's processes whose command line matches ``pattern``;
        returns how many (pkill alone would reach other runs' processes too)."""
        ours = set(
            subprocess.run(
                ["ip", "netns", "pids", self.ns], capture_output=True, text=True
            ).stdout.split()
        )
        found = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True)
        victims = [pid for pid in found.stdout.split() if pid in ours]
        for pid in victims:
            subprocess.run(["kill", "-9", pid], capture_output=True)
        return len(victims)

    def close(self) -> None:
        # Kill exactly this namespace's processes: `ray stop` would also stop any other Ray
        # cluster on the machine (another test run's, say).
        pids = subprocess.run(["ip", "netns", "pids", self.ns], capture_output=True, text=True)
        for pid in pids.stdout.split():
            subprocess.run(["kill", "-9", pid], capture_output=True)
        subprocess.run(["ip", "netns", "del", self.ns], capture_output=True)
        shutil.rmtree(self.tmp, ignore_errors=True)
