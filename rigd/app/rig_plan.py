"""The data rates a rig config will produce, for the checks that compare them with the machine.

Sizes are estimates: a frame is width x height x (1 for mono8 and bayer_rg8, 3 otherwise) bytes
(width/height from the spec's query, else `DEFAULT_FRAME`), an event is `EVENT_BYTES` in the take
at `DEFAULT_EVENT_RATE` unless the sensor's ERC caps it lower.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.registry import DeviceSpec
from rigd.app.config import RigConfig
from rigd.core.errors import ConfigError
from rigd.core.pixels import BYTES_PER_PIXEL

#: Frame size assumed when a camera spec does not say (a common 2.3 MP machine-vision sensor).
DEFAULT_FRAME = (1920, 1200)


#: Event rate assumed per sensor when its ERC does not cap it (busy scene, events/s).
DEFAULT_EVENT_RATE = 10e6


#: Bytes per event in a take: x, y uint16, p uint8, t int64 (before compression).
EVENT_BYTES = 13


@dataclass(frozen=True, slots=True)
class Plan:
    """Data rates the configured rig will produce."""

    bytes_per_s: float
    usb_cameras: list[tuple[str, int]]  # (name, bytes per frame) through userspace USB
    event_sensors_usb: int
    gige_cameras: list[str]
    node_paths: list[str]


def plan_rig(rig: RigConfig) -> Plan:
    """Bytes per second and the USB/GigE load of a rig config (see the module docstring)."""
    rate_hz = rig.trigger.settings.rate_hz
    total = 0.0
    usb: list[tuple[str, int]] = []
    gige: list[str] = []
    nodes: list[str] = []
    trig = spec_or_none(rig.trigger.spec)
    if trig is not None and trig.scheme == "serial":
        nodes.append(trig.path or trig.location)
    for cam in rig.cameras:
        spec = spec_or_none(cam.spec)
        params = spec.params if spec else {}
        width = int(params.get("width", DEFAULT_FRAME[0]))
        height = int(params.get("height", DEFAULT_FRAME[1]))
        fmt = cam.settings.pixel_format or params.get("format", "rgb8")
        frame_bytes = width * height * BYTES_PER_PIXEL.get(fmt, 3)
        fps = rate_hz if cam.settings.trigger_mode == "hardware" else cam.settings.free_run_fps
        total += frame_bytes * fps
        if spec is None:
            continue
        if spec.scheme == "genicam":
            # GigE or USB3 Vision: unknown until opened; count it for both limits.
            usb.append((cam.name, frame_bytes))
            gige.append(cam.name)
        elif spec.scheme == "v4l2":
            nodes.append(spec.path)
    n_ev_usb = 0
    for sen in rig.event_sensors:
        total += (sen.settings.erc_rate_ev_s or DEFAULT_EVENT_RATE) * EVENT_BYTES
        spec = spec_or_none(sen.spec)
        if spec is not None and spec.scheme == "prophesee":
            n_ev_usb += 1
    return Plan(total, usb, n_ev_usb, gige, nodes)


def spec_or_none(spec: str) -> DeviceSpec | None:
    """The parsed spec, or None when it does not parse (the estimate skips it; config checks report it)."""
    try:
        return DeviceSpec.parse(spec)
    except ConfigError:
        return None
