"""Hosts on a private test network, made of Linux network namespaces joined by veth pairs.

One server host (``srv``) and worker hosts (``w1``, ``w2``, ...). Each worker host has its own link to the server
host, and the test process (the root namespace) one more, to reach the server host's services. Addresses are
private to these namespaces: ``10.251.<i>.0/24`` between ``srv`` and ``w<i>``, and a ``/30`` in ``10.250.0.0/16``
(one not in use here) between this process and ``srv``. Everything is removed when the context ends, failure or
not: deleting a namespace deletes its veth ends, and with them their peers.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field


class NetworkUnavailable(RuntimeError):
    """This machine cannot make namespaces (not root, no iproute2, no permission in a container)."""


def _ip(*args: str) -> None:
    done = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        raise NetworkUnavailable(f"ip {' '.join(args)}: {done.stderr.strip()}")


@dataclass
class WorkerHost:
    namespace: str
    link: str  # its end of the link to the server host
    server_address: str  # the server host's address as this host reaches it


@dataclass
class PrivateNetwork:
    server_namespace: str
    server_address: str  # as the test process reaches it
    workers: list[WorkerHost] = field(default_factory=list)

    @staticmethod
    def wrap(namespace: str) -> list[str]:
        """The prefix that runs a command on that host."""
        return ["ip", "netns", "exec", namespace]

    def unplug(self, host: WorkerHost) -> None:
        """Take the host off the network, as a machine that lost power or its cable."""
        _ip("-n", host.namespace, "link", "set", "dev", host.link, "down")


def _free_subnet() -> int:
    used = subprocess.run(["ip", "-4", "-o", "addr"], capture_output=True, text=True, timeout=30).stdout
    for n in range(uuid.uuid4().int % 200, 256):
        if f" 10.250.{n}." not in used:
            return n
    raise NetworkUnavailable("every 10.250.x.0/30 is in use here")


@contextmanager
def private_network(workers: int) -> Iterator[PrivateNetwork]:
    if shutil.which("ip") is None:
        raise NetworkUnavailable("the ip command (iproute2) is not installed")
    if os.geteuid() != 0:
        raise NetworkUnavailable("making network namespaces needs root")
    tag = uuid.uuid4().hex[:6]
    server_ns = f"symgs-{tag}-srv"
    namespaces: list[str] = []
    root_link = f"sg{tag}r"
    try:
        for ns in [server_ns, *(f"symgs-{tag}-w{i}" for i in range(1, workers + 1))]:
            _ip("netns", "add", ns)
            namespaces.append(ns)
            _ip("-n", ns, "link", "set", "dev", "lo", "up")
        n = _free_subnet()
        _ip("link", "add", root_link, "type", "veth", "peer", "name", f"sg{tag}s0", "netns", server_ns)
        _ip("addr", "add", f"10.250.{n}.1/30", "dev", root_link)
        _ip("link", "set", "dev", root_link, "up")
        _ip("-n", server_ns, "addr", "add", f"10.250.{n}.2/30", "dev", f"sg{tag}s0")
        _ip("-n", server_ns, "link", "set", "dev", f"sg{tag}s0", "up")
        network = PrivateNetwork(server_ns, f"10.250.{n}.2")
        for i, ns in enumerate(namespaces[1:], start=1):
            near, far = f"sg{tag}s{i}", f"sg{tag}w{i}"
            _ip("-n", server_ns, "link", "add", near, "type", "veth", "peer", "name", far, "netns", ns)
            _ip("-n", server_ns, "addr", "add", f"10.251.{i}.1/24", "dev", near)
            _ip("-n", server_ns, "link", "set", "dev", near, "up")
            _ip("-n", ns, "addr", "add", f"10.251.{i}.2/24", "dev", far)
            _ip("-n", ns, "link", "set", "dev", far, "up")
            network.workers.append(WorkerHost(ns, far, f"10.251.{i}.1"))
        yield network
    finally:
        for ns in reversed(namespaces):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        subprocess.run(["ip", "link", "del", root_link], capture_output=True, timeout=30)  # gone with srv already
