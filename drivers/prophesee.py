"""`prophesee://SERIAL` through OpenEB's Python HAL (`metavision_hal`), when installed.

The HAL hands out raw EVT buffers (`I_EventsStream.get_latest_raw_data`); the camera is a
`DecodingEventSensor`, so they go through rigd's own decoder, exactly like the simulated
sensor's stream. The HAL facilities used for configuration (trigger-in, camera
synchronization, biases, ROI, ERC) are optional per camera model: asking for one the camera
lacks is a ConfigError naming it.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from drivers.base import Capability
from drivers.evt_stream import DecodingEventSensor, EvtBuffer
from drivers.lifecycle import END, Signal
from drivers.registry import DeviceSpec
from rigd.core.devices import DeviceInfo
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError
from rigd.core.settings import EventSensorSettings

log = logging.getLogger(__name__)

_FORMATS = {"EVT3": "evt3", "EVT2": "evt2", "EVT21": "evt21", "EVT2.1": "evt21", "EVT3.0": "evt3"}


def _import_hal() -> Any:
    try:
        import metavision_hal
    except ImportError as exc:
        raise BackendUnavailableError(
            "prophesee:// needs OpenEB's Python bindings (module metavision_hal), which are not "
            "installed. Install OpenEB (https://github.com/prophesee-ai/openeb, with Python bindings) "
            "and make sure `python -c 'import metavision_hal'` works in this environment."
        ) from exc
    return metavision_hal


class PropheseeSensor(DecodingEventSensor[EvtBuffer]):
    """A live camera opened with the HAL; the HAL is polled on the acquisition thread, so
    every HAL call after start happens there. A buffer the full host queue gives up is counted
    (`buffers_lost`, `bytes_lost`; its events are unknown until decoded)."""

    _overflow_name = "buffers_lost"

    def __init__(self, serial: str, *, buffers: int = 256, spec: str = "", strict: bool = False) -> None:
        hal = _import_hal()
        self._hal = hal
        device = hal.DeviceDiscovery.open(serial)
        if device is None:
            raise DeviceError(
                f"no Prophesee camera with serial {serial!r} (prophesee:// with empty serial opens the first)"
            )
        self._device = device
        geom = device.get_i_geometry()
        geometry = (int(geom.get_width()), int(geom.get_height()))
        ident = device.get_i_hw_identification()
        self._serial = str(ident.get_serial()) if ident is not None else serial
        fmt = "EVT3"
        if ident is not None and hasattr(ident, "get_current_data_encoding_format"):
            fmt = str(ident.get_current_data_encoding_format()).upper()
        if fmt not in _FORMATS:
            raise DeviceError(f"camera {self._serial} streams {fmt}, which rigd does not decode")
        fmt = _FORMATS[fmt]
        self._info = DeviceInfo(
            kind="event_sensor",
            spec=spec or f"prophesee://{serial}",
            vendor="Prophesee",
            model=str(ident.get_sensor_info())
            if ident is not None and hasattr(ident, "get_sensor_info")
            else "",
            serial=self._serial,
            firmware=f"format={fmt}",
            facts={"evt_format": fmt, "width": str(geometry[0]), "height": str(geometry[1])},
        )
        caps = {Capability.DEVICE_TIMESTAMPS}
        if device.get_i_trigger_in() is not None:
            caps.add(Capability.TRIGGER_IN)
        if device.get_i_camera_synchronization() is not None:
            caps.add(Capability.CLOCK_SYNC)
        self._capabilities = frozenset(caps)
        self._stream = device.get_i_events_stream()
        self._streaming = False
        self._lost_bytes = 0
        # the capture reads every few ms (`read_interval_ms`): what the HAL handed out meanwhile
        # comes as one buffer
        super().__init__(fmt, geometry, buffers=buffers, merge=64, drain_on_stop=True, strict=strict)

    def _facility(self, getter: str, what: str) -> Any:
        fac = getattr(self._device, getter)()
        if fac is None:
            raise ConfigError(f"camera {self._serial} has no {what} facility ({getter})")
        return fac

    def _do_configure(self, settings: EventSensorSettings) -> None:
        if settings.enable_trigger_in:
            trig = self._facility("get_i_trigger_in", "trigger-in")
            if not trig.enable(settings.trigger_in_channel):
                raise ConfigError(
                    f"camera {self._serial}: trigger-in channel {settings.trigger_in_channel} refused"
                )
        if settings.sync_mode != "standalone":
            sync = self._facility("get_i_camera_synchronization", "camera synchronization")
            ok = sync.set_mode_master() if settings.sync_mode == "master" else sync.set_mode_slave()
            if not ok:
                raise ConfigError(f"camera {self._serial}: sync mode {settings.sync_mode} refused")
        if settings.biases:
            biases = self._facility("get_i_ll_biases", "bias")
            for name, value in settings.biases.items():
                if not biases.set(name, int(value)):
                    raise ConfigError(f"camera {self._serial}: bias {name}={value} refused")
        if settings.roi is not None:
            roi = self._facility("get_i_roi", "ROI")
            x, y, w, h = settings.roi
            roi.set_window(self._hal.I_ROI.Window(x, y, w, h))
            roi.enable(True)
        if settings.erc_rate_ev_s is not None:
            erc = self._facility("get_i_erc_module", "event rate controller")
            erc.enable(True)
            erc.set_cd_event_rate(int(settings.erc_rate_ev_s))

    def _do_start(self) -> None:
        self._stream.start()
        self._streaming = True

    def _grab(self, timeout_s: float) -> EvtBuffer | Signal | None:
        if self._stopping:  # stop the stream from the thread that polls it
            self._stop_stream()
            return END
        if self._stream.poll_buffer() < 0:
            time.sleep(0.001)
            return None
        data = self._stream.get_latest_raw_data()
        if data is None or len(data) == 0:
            return None
        return EvtBuffer(bytes(data), time.monotonic_ns())

    def _deliver(self, item: EvtBuffer) -> bool:
        lost = self._queue.put(item)
        if lost is None:
            return True
        self._lost_bytes += len(lost.data)
        log.warning("camera %s: host buffer full, a raw buffer was lost", self._serial)
        return False

    def _do_close(self) -> None:
        self._stop_stream()  # when the polling thread died before it could
        super()._do_close()

    def _stop_stream(self) -> None:
        if self._streaming:
            self._streaming = False
            self._stream.stop()

    def _counters(self) -> tuple[int, dict[str, int]]:
        # Events inside lost buffers are unknown until decoded: the base counts what is known,
        # the buffers (`buffers_lost`, in device_dropped).
        extra = {"bytes_lost": self._lost_bytes}
        erc = self._device.get_i_erc_module()
        if erc is not None and hasattr(erc, "get_count_period"):
            extra["erc_enabled"] = int(bool(erc.is_enabled()))
        _, decoder = super()._counters()
        return 0, {**extra, **decoder}


def open_prophesee_sensor(spec: DeviceSpec) -> PropheseeSensor:
    """Factory for `prophesee://SERIAL?buffers=256` (empty serial: the first camera found)."""
    spec.check_params({"buffers", "strict"})
    serial = spec.location or spec.path.strip("/")
    return PropheseeSensor(
        serial,
        buffers=spec.int_param("buffers", 256),
        spec=spec.raw,
        strict=bool(spec.int_param("strict", 0)),
    )
