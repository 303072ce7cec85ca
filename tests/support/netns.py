"""Private network namespaces for the cross-process tests (``tests/crossprocess/``): the loopback setup that carries
``udp_multicast`` inside one, and the probes that say why a namespace cannot be created here (the test then skips with
that reason).
"""

from __future__ import annotations

import shutil
import subprocess

NETNS_SETUP = "ip link set lo up; ip link set lo multicast on; ip route add 224.0.0.0/4 dev lo"


def unshare_available() -> str | None:
    """None when ``unshare --net`` and :data:`NETNS_SETUP` inside it work here, else why not."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is not installed"
    probe = subprocess.run(
        ["unshare", "--net", "--", "sh", "-c", NETNS_SETUP], capture_output=True, text=True, timeout=30
    )
    if probe.returncode != 0:
        return f"unshare --net is not permitted here: {probe.stderr.strip() or probe.returncode}"
    return None


def namespaces_allowed() -> str | None:
    """None if ``unshare --net`` works here (nothing run inside it), else the reason it does not."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is not installed"
    probe = subprocess.run(["unshare", "--net", "--", "true"], capture_output=True, text=True, timeout=10)
    if probe.returncode != 0:
        return f"unshare --net is not permitted here: {probe.stderr.strip()}"
    return None
