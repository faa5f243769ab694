"""A CAN bus that the processes of one machine share: python-can interface `dojo_host` (the package registers it
as a `can.interface` entry point), for the emulator, where hardware has one CAN adapter that several processes
open (SocketCAN allows that) and the console's e-stop process (`dojo.realeval.estop`) needs a connection to the
arms of its own.

Why not python-can's own interfaces: `virtual` reaches only its own process; a kernel `vcan` port needs the
`vcan` module and CAP_NET_ADMIN (the machines here have neither; and piper-sdk 0.6.2 opens its sockets without
local loopback, see piper_driver); `udp_multicast` takes its port as a keyword the SDK cannot pass
(`CreateCanBus` forwards only channel and interface), and Linux delivers a datagram for any group joined on the
machine to every socket bound to its port (IP_MULTICAST_ALL, IPv4 and IPv6 alike, checked here), so two channels
on the default port are one bus: the PiPER's two arms would hear each other's commands.

Each bus of channel C is a UDP socket on 127.0.0.1 (so nothing leaves the machine), listed as a file
`<pid>-<port>` in `<tmp>/dojo-can-<uid>/C/`; a frame goes to every other bus listed there. Like a CAN socket, a
reader whose buffer is full loses the frame and a reader that has gone costs nothing (UDP drops both; files of
processes that have exited are removed). A frame is stamped when it is sent (wall clock, as python-can's
`virtual` bus stamps it), so its `timestamp` is when it went on the bus.
"""

from __future__ import annotations

import os
import re
import select
import socket
import struct
import tempfile
import time
from pathlib import Path
from typing import Any

import can

INTERFACE = "dojo_host"
FRAME = struct.Struct("<dIBB8s")
"""Wire format: send time (wall clock), arbitration id, flags (EXTENDED | REMOTE | ERROR), data length, data."""
EXTENDED, REMOTE, ERROR = 1, 2, 4
RECENT_NS = 100_000_000
"""A folder changed this recently is listed again at every send: its time stamp is coarse (a clock tick), so a
bus that joined in the same tick as the last listing would not change it."""
CHANNEL_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def channel_dir(channel: str) -> Path:
    """Where the buses of `channel` are listed (private to this user)."""
    if not CHANNEL_NAME.match(channel):
        raise ValueError(f"dojo_host CAN channel {channel!r}: letters, digits, '_', '.', '-' only (1-64)")
    root = Path(tempfile.gettempdir()) / f"dojo-can-{os.getuid()}"
    root.mkdir(mode=0o700, exist_ok=True)
    folder = root / channel
    folder.mkdir(mode=0o700, exist_ok=True)
    return folder


class HostBus(can.BusABC):
    """One connection to channel `channel` of this machine's shared CAN buses (see the module docstring)."""

    def __init__(self, channel: str, **kwargs: Any) -> None:
        self._folder = channel_dir(str(channel))
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.bind(("127.0.0.1", 0))
        self._socket.setblocking(False)
        self._entry = self._folder / f"{os.getpid()}-{self._socket.getsockname()[1]}"
        self._entry.touch()
        self._peers: list[tuple[str, int]] = []
        self._listing = -1
        self.channel_info = f"dojo_host {channel}"
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_fd or len(msg.data) > 8:
            raise can.CanOperationError("dojo_host carries classic CAN frames (8 data bytes at most)")
        flags = (EXTENDED if msg.is_extended_id else 0) | (REMOTE if msg.is_remote_frame else 0) \
            | (ERROR if msg.is_error_frame else 0)
        payload = FRAME.pack(time.time(), msg.arbitration_id, flags, msg.dlc, bytes(msg.data).ljust(8, b"\0"))
        for peer in self._listed_peers():
            try:
                self._socket.sendto(payload, peer)
            except OSError:  # a full or vanished reader: the frame is lost for it, as on a CAN socket
                pass

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            data = self._socket.recv(FRAME.size)
        except BlockingIOError:
            if timeout == 0 or not select.select([self._socket], [], [], timeout)[0]:
                return None, False
            data = self._socket.recv(FRAME.size)
        stamp, arbitration_id, flags, dlc, payload = FRAME.unpack(data)
        return can.Message(timestamp=stamp, arbitration_id=arbitration_id, is_extended_id=bool(flags & EXTENDED),
                           is_remote_frame=bool(flags & REMOTE), is_error_frame=bool(flags & ERROR), dlc=dlc,
                           data=payload[:dlc], channel=self.channel_info, is_rx=True), False

    def _listed_peers(self) -> list[tuple[str, int]]:
        """The other buses of the channel (read again whenever the folder changes)."""
        listing = self._folder.stat().st_mtime_ns
        if listing != self._listing or time.time_ns() - listing < RECENT_NS:
            peers = []
            for entry in self._folder.iterdir():
                pid, _, port = entry.name.partition("-")
                if entry == self._entry or not (pid.isdigit() and port.isdigit()):
                    continue
                if not _alive(int(pid)):
                    entry.unlink(missing_ok=True)
                    continue
                peers.append(("127.0.0.1", int(port)))
            self._peers, self._listing = peers, listing
        return self._peers

    def fileno(self) -> int:
        return self._socket.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._entry.unlink(missing_ok=True)
        self._socket.close()
        try:
            self._folder.rmdir()  # the channel's last bus: leave no folder behind
        except OSError:
            pass  # other buses are still on it


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
