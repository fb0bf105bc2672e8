"""Stream tracked poses to a navigation system over OpenIGTLink (3D Slicer's OpenIGTLinkIF, the PLUS toolkit).

Every frame sends a STRING message on the status device (``tracked``, ``relocalised`` or ``lost``) and one on the
reason device (why a lost frame is lost: ``hidden``, ``no depth``, ... as in track.jsonl; empty when it has a pose)
and one on the unmeasured device (what the frame's data left free, as in track.jsonl's ``unmeasured``: ``turn``,
``slide`` or ``slide turn``; empty when nothing, or lost) and one on the colour device (how instrument-like the
mask the tracker made for the frame looks, as in track.jsonl's ``colour``: ``0.870``; empty with a given mask, or
lost);
a frame with a pose also sends a TRANSFORM message on the pose device: the object-to-camera pose with its
translation in millimetres, the unit Slicer and PLUS use. A lost frame sends no transform, so a receiver keeps the
last valid one and reads the status to know it is stale. The reason has a device of its own so that a receiver
comparing the status to ``lost`` reads the same strings as before. pyigtl's server serves one client at a time;
frames tracked while no client is connected are not queued (a navigation system wants the current pose, not a
backlog).
"""

from __future__ import annotations

import signal
import threading
import time
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the CLI reads the default device names without loading the tracker
    from .tracker import TrackResult

DEFAULT_DEVICE = "InstrumentToCamera"
DEFAULT_STATUS_DEVICE = "TrackingStatus"
DEFAULT_REASON_DEVICE = "TrackingLostReason"
DEFAULT_UNMEASURED_DEVICE = "TrackingUnmeasured"
DEFAULT_COLOUR_DEVICE = "TrackingMaskColour"
IGTL_DEVICE_NAME_BYTES = 20  # the header's device-name field


def _check_name(name: str) -> str:
    try:
        encoded = name.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"OpenIGTLink device name {name!r} must be ASCII") from None
    if not 0 < len(encoded) <= IGTL_DEVICE_NAME_BYTES:
        raise ValueError(f"OpenIGTLink device name {name!r} must have 1 to {IGTL_DEVICE_NAME_BYTES} characters")
    return name


def pose_to_igtl(pose: np.ndarray) -> np.ndarray:
    """4x4 pose in metres -> the TRANSFORM matrix (same rotation, translation in millimetres)."""
    matrix = np.array(pose, dtype=np.float64, copy=True)
    matrix[:3, 3] *= 1000.0
    return matrix


class PoseStreamer:
    """An OpenIGTLink server sending each frame's result.

    It listens on 127.0.0.1, or on the address of network ``interface`` (e.g. "eth0") for a navigation system on
    another machine; ``port`` 0 picks a free port (see :attr:`port`).
    """

    def __init__(self, port: int = 18944, device_name: str = DEFAULT_DEVICE,
                 status_device: str = DEFAULT_STATUS_DEVICE, interface: str | None = None,
                 reason_device: str = DEFAULT_REASON_DEVICE, unmeasured_device: str = DEFAULT_UNMEASURED_DEVICE,
                 colour_device: str = DEFAULT_COLOUR_DEVICE):
        import pyigtl

        self._pyigtl = pyigtl
        names = [device_name, status_device, reason_device, unmeasured_device, colour_device]
        (self.device_name, self.status_device, self.reason_device, self.unmeasured_device,
         self.colour_device) = map(_check_name, names)
        if len(set(names)) < len(names):
            raise ValueError(f"OpenIGTLink device names {', '.join(map(repr, names))} must differ")
        main_thread = threading.current_thread() is threading.main_thread()
        signals = (signal.SIGINT, signal.SIGTERM)
        saved = {s: signal.getsignal(s) for s in signals} if main_thread else {}
        self._server = pyigtl.OpenIGTLinkServer(port=port, local_server=interface is None, iface=interface)
        for s, handler in saved.items():  # pyigtl installs handlers that close the server and re-raise; keep ours
            signal.signal(s, handler)
        self.port = int(self._server.server_address[1])
        self.sent = 0

    @property
    def connected(self) -> bool:
        """Whether a client is connected."""
        return bool(self._server.is_connected())

    def send(self, result: TrackResult, timestamp: float | None = None) -> bool:
        """Send one frame's status, lost reason, unmeasured directions and made mask's colour (and transform when
        it has a pose); False when no client is connected."""
        if not self.connected:
            return False
        igtl = self._pyigtl
        if result.pose is not None:
            matrix = pose_to_igtl(result.pose)
            self._server.send_message(igtl.TransformMessage(matrix, timestamp=timestamp, device_name=self.device_name),
                                      wait=False)
        self._server.send_message(igtl.StringMessage(result.status, timestamp=timestamp,
                                                     device_name=self.status_device), wait=False)
        self._server.send_message(igtl.StringMessage(result.reason, timestamp=timestamp,
                                                     device_name=self.reason_device), wait=False)
        self._server.send_message(igtl.StringMessage(" ".join(result.unmeasured_kinds), timestamp=timestamp,
                                                     device_name=self.unmeasured_device), wait=False)
        colour = "" if result.colour is None else f"{result.colour:.3f}"
        self._server.send_message(igtl.StringMessage(colour, timestamp=timestamp, device_name=self.colour_device),
                                  wait=False)
        self.sent += 1
        return True

    def close(self, flush_s: float = 1.0) -> None:
        """Send what is queued (waiting at most ``flush_s`` seconds), stop the server and free the port."""
        if self._server is not None:
            deadline = time.monotonic() + flush_s
            while self._server.outgoing_messages and self.connected and time.monotonic() < deadline:
                time.sleep(0.005)
            self._server.stop()
            self._server = None

    def __enter__(self) -> PoseStreamer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
