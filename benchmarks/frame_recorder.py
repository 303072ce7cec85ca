"""The independent receiver: every frame on a ``udp_multicast`` bus with its kernel timestamp, in a process of its own.

The instrument of the realtime benchmarks (:mod:`benchmarks.realtime`, :mod:`benchmarks.realtime_axes`) and of the
cross-process latched-truth test (``tests/support/latched_crossprocess_script.py``). It imports python-can and nothing
of this project, so what it records is what was on the wire, not what the bench's code believes.

``python -m benchmarks.frame_recorder GROUP OUT`` (only inside a private network namespace: it joins ``GROUP``):
prints ``listening`` once its socket is joined, records until SIGTERM, writes ``OUT`` and prints ``dropped N``.
Its socket gets a 16 MiB receive buffer (the default 208 KiB holds about 0.1 s of a 1 kHz bench's traffic: a stall
of the recorder longer than that dropped datagrams, which then read as frames the bench lost), and ``N`` is how many
datagrams the socket still dropped (``/proc/net/udp``'s ``drops`` of its inode; -1: not found), so a frame it
missed is never taken for one the bench or a drive lost.

``OUT`` is one JSON document, the one format: ``{"frames": [[arbitration_id, timestamp, data_hex], ...],
"dropped": N}`` in the order received. :func:`start` and :func:`stop` run it from another process;
:class:`Recording` reads it back.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["RECEIVE_BUFFER", "Recording", "main", "start", "stop"]

RECEIVE_BUFFER = 1 << 24
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)  # Linux's; Python names it from 3.12 on
ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Recording:
    """What the recorder saw.

    Attributes
    ----------
    frames
        ``(n, 2)``: arbitration id and kernel receive timestamp (wall clock, seconds) of each frame, in order.
    data
        Each frame's data bytes.
    dropped
        Datagrams its socket dropped; None: it did not say (it was killed, or its socket was not found).
    """

    frames: np.ndarray
    data: list[bytes]
    dropped: int | None

    @classmethod
    def load(cls, path: Path) -> Recording:
        document = json.loads(path.read_text(encoding="utf-8"))
        rows = document["frames"]
        frames = np.array([(row[0], row[1]) for row in rows], dtype=float).reshape(-1, 2)
        dropped = document.get("dropped")
        return cls(frames, [bytes.fromhex(row[2]) for row in rows],
                   None if dropped is None or dropped < 0 else int(dropped))

    def of(self, can_id: int) -> np.ndarray:
        """The timestamps of the frames with ``can_id``."""
        return self.frames[self.frames[:, 0] == can_id, 1]


def _dropped(sock: socket.socket) -> int:
    inode = os.fstat(sock.fileno()).st_ino
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        with open(table, encoding="ascii") as rows:
            for line in list(rows)[1:]:
                fields = line.split()
                if int(fields[9]) == inode:
                    return int(fields[-1])
    return -1


def main(argv: Sequence[str] | None = None) -> int:
    """Record (module docstring)."""
    import can

    group, out = (sys.argv[1:] if argv is None else list(argv))[:2]
    bus = can.Bus(interface="udp_multicast", channel=group)
    with socket.socket(fileno=os.dup(bus.fileno())) as sock:  # the same socket (a duplicate descriptor)
        try:  # root may go past net.core.rmem_max
            sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, RECEIVE_BUFFER)
        except OSError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        stopped: list[int] = []
        signal.signal(signal.SIGTERM, lambda *_: stopped.append(1))
        rows = []
        print("listening", flush=True)
        while not stopped:
            message = bus.recv(0.1)
            if message is not None:
                rows.append((message.arbitration_id, message.timestamp, bytes(message.data).hex()))
        dropped = _dropped(sock)
    bus.shutdown()
    Path(out).write_text(json.dumps({"frames": rows, "dropped": dropped}), encoding="utf-8")
    print("dropped", dropped, flush=True)
    return 0


def start(group: str, out: Path, *, fifo: int | None = None) -> subprocess.Popen[str]:
    """Start the recorder (under ``chrt -f FIFO`` when given); returns once its socket is joined."""
    prefix = ["chrt", "-f", str(fifo)] if fifo is not None else []
    recorder = subprocess.Popen([*prefix, sys.executable, "-m", "benchmarks.frame_recorder", group, str(out)],
                                stdout=subprocess.PIPE, text=True, cwd=ROOT,
                                env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert recorder.stdout is not None
    line = recorder.stdout.readline()
    if "listening" not in line:
        recorder.kill()
        recorder.wait()
        raise RuntimeError(f"the frame recorder did not start: {line!r}")
    return recorder


def stop(recorder: subprocess.Popen[str], out: Path) -> Recording:
    """Stop the recorder (SIGTERM) and read what it wrote."""
    recorder.send_signal(signal.SIGTERM)
    recorder.communicate(timeout=60)
    return Recording.load(out)


if __name__ == "__main__":
    raise SystemExit(main())
