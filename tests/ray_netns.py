"""A local multi-node Ray cluster inside a network namespace (tests and bench).

Every process of the cluster, and the driver run through :meth:`Cluster.sh`, lives in a
namespace whose only interface is loopback, so all traffic stays on 127.0.0.1. Needs root
and iproute2 (``ip netns``).

The cluster is hermetic: its own temp dir and ``HOME`` (so nothing reads or writes
``~/.ray``, where Ray keeps a token after its first local cluster), and an explicit
authentication setting given to every node and driver (``RAY_AUTH_MODE``, and with
``token=`` the ``RAY_AUTH_TOKEN``). A cluster that fails to start half-way is torn down
before the error propagates: no process, namespace or temp dir is left behind.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import uuid
from collections.abc import Mapping
from pathlib import Path

BIN = Path(sys.executable).parent
PORT = 6391

#: Environment variables through which Ray picks up a cluster or credentials; a cluster's
#: processes get them only from :class:`Cluster`, never from the caller's environment.
RAY_ENV = ("RAY_ADDRESS", "RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")


class ClusterError(RuntimeError):
    """A cluster command failed; the message holds its stderr's tail."""


def netns_available() -> bool:
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return False
    name = f"bopsurg-probe-{uuid.uuid4().hex[:6]}"
    ok = subprocess.run(["ip", "netns", "add", name], capture_output=True).returncode == 0
    if ok:
        subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return ok


def netns_exists(name: str) -> bool:
    out = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    return any(line.split()[0] == name for line in out.splitlines() if line.strip())


def netns_pids(name: str) -> list[str]:
    out = subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True)
    return out.stdout.split()


def auth_env(token: str | None) -> dict[str, str]:
    """The explicit authentication setting of a node or driver: token auth with ``token``,
    or none (``RAY_AUTH_MODE=disabled``)."""
    if token is None:
        return {"RAY_AUTH_MODE": "disabled"}
    return {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token}


class Cluster:
    """A head and ``nodes - 1`` worker nodes in a fresh network namespace.

    Args:
        nodes: Nodes, the head included.
        cpus_per_node: CPUs each node offers.
        token: Token authentication with this token on every node and on the drivers of
            :meth:`sh`; None runs the cluster without authentication.
        node_env: Extra environment for the non-head nodes only (tests use it to make a
            node fail to join).
    """

    def __init__(
        self,
        nodes: int = 2,
        cpus_per_node: int = 1,
        *,
        token: str | None = None,
        node_env: Mapping[str, str] | None = None,
    ) -> None:
        self.ns = f"bopsurg-ray-{uuid.uuid4().hex[:6]}"
        self.tmp = Path("/tmp") / f"rb{uuid.uuid4().hex[:6]}"  # short: socket path limits
        self.token = token
        self.address = f"127.0.0.1:{PORT}"
        home = self.tmp / "home"
        base = {k: v for k, v in os.environ.items() if k not in RAY_ENV}
        self.env = {
            **base,
            "PATH": f"{BIN}:{os.environ['PATH']}",
            "HOME": str(home),
            # temporary files too (a worker killed mid-load leaves its scene folder), so that
            # close() removes them with the rest
            "TMPDIR": str(self.tmp / "tmp"),
            "RAY_USAGE_STATS_ENABLED": "0",
            **auth_env(token),
        }
        self._ns_made = False
        try:
            home.mkdir(parents=True)
            (self.tmp / "tmp").mkdir()
            subprocess.run(["ip", "netns", "add", self.ns], check=True, capture_output=True)
            self._ns_made = True
            self.sh("ip link set lo up")
            common = f"--num-cpus={cpus_per_node} --disable-usage-stats --node-ip-address=127.0.0.1"
            head = f"--head --port={PORT} --include-dashboard=false --temp-dir={self.tmp}/ray"
            self.sh(f"ray start {head} {common}")
            for _ in range(nodes - 1):
                self.sh(f"ray start --address={self.address} {common}", env=node_env)
        except BaseException:
            self.close()
            raise

    def sh(
        self,
        cmd: str,
        *,
        check: bool = True,
        background: bool = False,
        env: Mapping[str, str | None] | None = None,
    ):
        """Run ``cmd`` with bash inside the namespace, in the cluster's environment updated
        by ``env`` (a None value removes the variable). Raises :class:`ClusterError` with
        the command's stderr when ``check`` and it fails."""
        args = ["ip", "netns", "exec", self.ns, "bash", "-c", cmd]
        run_env = dict(self.env)
        for key, value in (env or {}).items():
            if value is None:
                run_env.pop(key, None)
            else:
                run_env[key] = value
        if background:
            return subprocess.Popen(
                args, env=run_env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
            )
        r = subprocess.run(args, env=run_env, capture_output=True, text=True)
        if check and r.returncode != 0:
            raise ClusterError(f"`{cmd}` exited {r.returncode}: {r.stderr[-3000:]}")
        return r

    def kill(self, pattern: str) -> int:
        """SIGKILL this namespace's processes whose command line matches ``pattern``;
        returns how many (pkill alone would reach other runs' processes too)."""
        ours = set(netns_pids(self.ns))
        found = subprocess.run(["pgrep", "-f", pattern], capture_output=True, text=True)
        victims = [pid for pid in found.stdout.split() if pid in ours]
        for pid in victims:
            subprocess.run(["kill", "-9", pid], capture_output=True)
        return len(victims)

    def close(self) -> None:
        """Kill exactly this namespace's processes, delete it and the temp dir; safe to call
        on a half-started cluster and more than once (`ray stop` would also stop any other
        Ray cluster on the machine, another test run's, say)."""
        if self._ns_made:
            # Killed processes may have children that were forking: repeat until none is left.
            for _ in range(20):
                pids = netns_pids(self.ns)
                if not pids:
                    break
                subprocess.run(["kill", "-9", *pids], capture_output=True)
            subprocess.run(["ip", "netns", "del", self.ns], capture_output=True)
            self._ns_made = False
        shutil.rmtree(self.tmp, ignore_errors=True)
