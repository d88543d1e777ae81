"""The host end of a simulated box's pty that tells the box what the host has handled.

On the virtual clock the box holds the world at each pulse until the host has stamped its
record (`SimTriggerBox.host_handled`, decision 0038). The driver's receive thread reads,
handles (stamps) every complete line it got, and only then reads again; so each `read` first
reports the bytes its earlier reads returned: by then every line among them is stamped. A
box only learns that the kernel queue is empty otherwise, which happens before the stamp.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.trigger_link import SerialTransport

if TYPE_CHECKING:
    from firmware_sim.trigger_box import SimTriggerBox


class HandledPty(SerialTransport):
    """pyserial on the box's pty, reporting the bytes handled at each read."""

    def __init__(self, box: SimTriggerBox) -> None:
        super().__init__(box.port_path)
        self._box = box
        self._returned = 0
        box.host_handled(0)  # from now on the box waits for these reports, not the queue

    def read(self, timeout_s: float) -> bytes:
        self._box.host_handled(self._returned)
        data = super().read(timeout_s)
        self._returned += len(data)
        return data
