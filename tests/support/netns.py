"""Hosts on one machine: network namespaces joined by veth pairs to a bridge (iproute2, as root).

    with Network(["db", "api", "w1", "w2", "client"]) as net:
        net.address("db")                      # 198.18.0.1
        proc = net.popen("api", [...], log)    # a process on that host
        net.cut("w1"); net.restore("w1")       # pull and put back a host's cable

Every host is a namespace with loopback and one interface ``eth0`` on 198.18.0.0/24 (RFC 2544's
benchmarking range: no real network uses it, and these addresses exist only inside the
namespaces). The bridge lives in a namespace of its own, so the machine's own namespace gets no
address and no route to them. Cutting a host sets its bridge port down: packets to and from it
are dropped, its processes keep running, as when a cable or a switch port fails.

Everything is removed on exit, also after a failure: the processes started through
:meth:`Network.popen` (SIGKILL to their process group) and then the namespaces (deleting a
namespace deletes its veth ends). :func:`netns_unavailable` says why hosts cannot be made here.
"""

from __future__ import annotations

import os
import signal
import subprocess
import uuid
from pathlib import Path

__all__ = ["Network", "netns_unavailable", "SUBNET"]

SUBNET = "198.18.0"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=30)


def netns_unavailable() -> str | None:
    """None if namespaces can be made here, else the reason (not root, no iproute2, no netns)."""
    if os.geteuid() != 0:
        return "network namespaces need root (CI runs as root)"
    probe = f"bsp{uuid.uuid4().hex[:8]}"
    try:
        _ip("netns", "add", probe)
    except FileNotFoundError:
        return "iproute2's `ip` is not installed (apt-get install -y iproute2)"
    except subprocess.CalledProcessError as exc:
        return f"`ip netns add` failed: {exc.stderr.strip()}"
    _ip("netns", "del", probe)
    return None


class Network:
    """Named hosts on one bridge; a context manager that always cleans up."""

    def __init__(self, hosts: list[str]) -> None:
        self.prefix = f"bs{uuid.uuid4().hex[:6]}"
        self.hosts = list(hosts)
        self.switch = f"{self.prefix}-sw"
        self._made: list[str] = []
        self._procs: list[subprocess.Popen] = []

    def ns(self, host: str) -> str:
        return f"{self.prefix}-{host}"

    def address(self, host: str) -> str:
        return f"{SUBNET}.{self.hosts.index(host) + 1}"

    def _port(self, host: str) -> str:
        return f"{self.prefix}s{self.hosts.index(host)}"  # the host's port on the bridge

    def __enter__(self) -> "Network":
        try:
            _ip("netns", "add", self.switch)
            self._made.append(self.switch)
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
            for i, host in enumerate(self.hosts):
                ns = self.ns(host)
                _ip("netns", "add", ns)
                self._made.append(ns)
                _ip("-n", ns, "link", "set", "lo", "up")
                near, port = f"{self.prefix}h{i}", self._port(host)
                _ip("link", "add", near, "type", "veth", "peer", "name", port)
                _ip("link", "set", near, "netns", ns)
                _ip("link", "set", port, "netns", self.switch)
                _ip("-n", ns, "link", "set", near, "name", "eth0")
                _ip("-n", ns, "addr", "add", f"{self.address(host)}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", self.switch, "link", "set", port, "master", "br0")
                _ip("-n", self.switch, "link", "set", port, "up")
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def command(self, host: str, argv: list[str]) -> list[str]:
        """``argv`` run on ``host``."""
        return ["ip", "netns", "exec", self.ns(host), *argv]

    def popen(self, host: str, argv: list[str], log: Path, env: dict[str, str] | None = None,
              **kwargs) -> subprocess.Popen:
        """Start ``argv`` on ``host`` (its own process group, output to ``log``); killed on exit."""
        with open(log, "ab") as out:
            proc = subprocess.Popen(self.command(host, argv), stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env, start_new_session=True, **kwargs)
        self._procs.append(proc)
        return proc

    def run(self, host: str, argv: list[str], timeout: float = 60, **kwargs) -> subprocess.CompletedProcess:
        """Run ``argv`` on ``host`` to completion."""
        return subprocess.run(self.command(host, argv), capture_output=True, text=True, timeout=timeout, **kwargs)

    def cut(self, host: str) -> None:
        """Pull ``host``'s cable: its bridge port goes down."""
        _ip("-n", self.switch, "link", "set", self._port(host), "down")

    def restore(self, host: str) -> None:
        _ip("-n", self.switch, "link", "set", self._port(host), "up")

    @staticmethod
    def kill(proc: subprocess.Popen, sig: int = signal.SIGKILL) -> None:
        """Signal a process started by :meth:`popen` and its children (its process group)."""
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, sig)
            except ProcessLookupError:
                pass

    def close(self) -> None:
        for proc in self._procs:
            self.kill(proc)
        for proc in self._procs:
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                pass
        for ns in reversed(self._made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        self._made.clear()
