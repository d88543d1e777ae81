"""`genicam://SERIAL_OR_NAME` through Aravis (GigE Vision and USB3 Vision), when installed.

Aravis is reached through PyGObject (`gi.repository.Aravis`, Debian `gir1.2-aravis-0.8`);
both are optional and imported only when a genicam:// spec is opened.

Spec: `genicam://SERIAL_OR_ID_OR_IP?trigger_source=Line0&activation=RisingEdge&buffers=16&
roi=X,Y,W,H&packet_size=1400&interface=IP&socket_buffer=BYTES`. `interface` opens a GigE
camera directly by address from that host interface (no discovery broadcast: needed on
loopback, where Aravis otherwise picks the wrong interface; see docs/hardware.md).

Frames carry the camera's own counters: the GVSP/U3V block id as `frame_counter` (gaps =
lost frames) and the device timestamp (ns, converted to us). Incomplete buffers (missing
packets, timeouts, size mismatch) are counted in `stats().device_dropped` and re-queued at
once, never leaked: a leaked buffer shrinks the pool until the stream starves (harvesters
#214 / #131). Aravis' own stream statistics (completed, failures, underruns, missing and
resent packets) go into `stats().extra`.
"""

from __future__ import annotations

import importlib
import ipaddress
import logging
import time
from typing import Any

import numpy as np

from drivers.base import Capability, RgbCamera
from drivers.registry import DeviceSpec
from rigd.core.devices import DeviceInfo
from rigd.core.errors import BackendUnavailableError, ConfigError, DeviceError
from rigd.core.frames import Frame
from rigd.core.settings import CameraSettings

log = logging.getLogger(__name__)

#: GenICam pixel format names of the settings' formats (SFNC names a Bayer format by its
#: top-left 2x2 block, as sensor data sheets do: BayerRG8 is an RGGB mosaic).
PIXEL_FORMATS = {"mono8": "Mono8", "rgb8": "RGB8", "bayer_rg8": "BayerRG8"}
#: The settings' format of each GenICam name, to tell what a camera sends by default.
_FORMAT_OF = {v: k for k, v in PIXEL_FORMATS.items()}
#: GenICam formats that make a camera a colour camera.
_COLOR_FORMATS = frozenset({PIXEL_FORMATS["rgb8"], PIXEL_FORMATS["bayer_rg8"]})
_STAT_NAMES = (
    "n_completed_buffers",
    "n_failures",
    "n_underruns",
    "n_timeouts",
    "n_aborted",
    "n_missing_frames",
    "n_size_mismatch_errors",
    "n_missing_packets",
    "n_resent_packets",
    "n_resend_requests",
)
#: Frames the host holds for the reader at least (more with more Aravis buffers).
DEFAULT_QUEUE = 64
_PARAMS = {"trigger_source", "activation", "buffers", "roi", "packet_size", "interface", "socket_buffer"}


def import_aravis() -> Any:
    """The Aravis GI module; BackendUnavailableError saying what to install otherwise."""
    try:
        gi = importlib.import_module("gi")
        gi.require_version("Aravis", "0.8")
        return importlib.import_module("gi.repository.Aravis")
    except (ImportError, ValueError) as exc:
        raise BackendUnavailableError(
            f"genicam:// needs Aravis 0.8 through PyGObject ({exc}): apt-get install gir1.2-aravis-0.8 "
            "libgirepository1.0-dev libcairo2-dev pkg-config && pip install PyGObject (docs/hardware.md)"
        ) from exc


def parse_roi(spec: DeviceSpec) -> tuple[int, int, int, int] | None:
    vals = spec.int_list_param("roi")
    if not vals:
        return None
    if len(vals) != 4 or vals[2] <= 0 or vals[3] <= 0 or min(vals) < 0:
        raise ConfigError(f"device spec {spec.raw!r}: roi must be X,Y,WIDTH,HEIGHT with positive size")
    return vals[0], vals[1], vals[2], vals[3]


class GenicamCamera(RgbCamera):
    """One Aravis camera in hardware-trigger (or free-run) mode, with a pool of re-queued buffers."""

    def __init__(
        self,
        spec: DeviceSpec,
        *,
        aravis: Any | None = None,
    ) -> None:
        spec.check_params(_PARAMS)
        self._n_buffers = spec.int_param("buffers", 16)
        if self._n_buffers < 2:
            raise ConfigError(f"device spec {spec.raw!r}: buffers must be >= 2")
        # Completed frames wait on the host once their Aravis buffer went back to the pool.
        super().__init__(
            CameraSettings(), queue_len=max(DEFAULT_QUEUE, 4 * self._n_buffers), drain_on_stop=True
        )
        self._spec = spec
        self._arv = aravis if aravis is not None else import_aravis()
        self.name = spec.location or spec.path.strip("/")
        self._label = f"genicam camera {self.name!r}"
        self._trigger_source = spec.param("trigger_source", "Line0")
        self._activation = spec.param("activation", "RisingEdge")
        self._roi = parse_roi(spec)
        self._stream: Any = None
        self._incomplete = 0
        self._counter_gaps = 0
        self._last_counter: int | None = None
        self._last_raw: int | None = None
        self._wraps = 0
        self._final_stats: dict[str, int] = {}
        self._cam = self._open(spec)
        dev = self._cam.get_device()
        self._dev = dev
        try:
            if self._cam.is_gv_device():
                self._tune_gige(spec)
            if self._roi is not None:
                self._cam.set_region(*self._roi)
            self._info = DeviceInfo(
                kind="rgb_camera",
                spec=spec.raw,
                vendor=str(self._cam.get_vendor_name() or ""),
                model=str(self._cam.get_model_name() or ""),
                serial=str(self._cam.get_device_serial_number() or ""),
                facts={
                    "sync": "hardware",
                    "transport": "GigEVision" if self._cam.is_gv_device() else "USB3Vision",
                    "trigger_source": self._trigger_source,
                    "aravis": self._aravis_version(),
                },
            )
            self._capabilities = self._probe_capabilities()
        except Exception as exc:
            self._cam = None
            raise DeviceError(f"genicam camera {self.name!r}: setup failed: {exc}") from exc
        log.info("genicam camera %s: %s %s", self.name, self._info.vendor, self._info.model)

    # ------------------------------------------------------------------ open
    def _open(self, spec: DeviceSpec) -> Any:
        arv = self._arv
        iface = spec.params.get("interface")
        try:
            if iface is not None:
                gio = importlib.import_module("gi.repository.Gio")
                try:
                    ipaddress.ip_address(self.name)
                    ipaddress.ip_address(iface)
                except ValueError:
                    raise ConfigError(
                        f"device spec {spec.raw!r}: with interface=, name the camera by its IP address"
                    ) from None
                dev = arv.GvDevice.new(
                    gio.InetAddress.new_from_string(iface), gio.InetAddress.new_from_string(self.name)
                )
                return arv.Camera.new_with_device(dev)
            arv.update_device_list()
            ids = [arv.get_device_id(i) for i in range(arv.get_n_devices())]
            serials = [arv.get_device_serial_nbr(i) for i in range(arv.get_n_devices())]
            target = self.name or None
            if target is not None and target not in ids:
                matches = [ids[i] for i, s in enumerate(serials) if s == target]
                if not matches:
                    raise DeviceError(
                        f"no GenICam camera {target!r}; found: {', '.join(ids) or 'none'} "
                        "(GigE: same subnet? `rigd devices`, `arv-tool-0.8`)"
                    )
                target = matches[0]
            return arv.Camera.new(target)
        except (ConfigError, DeviceError):
            raise
        except Exception as exc:  # GLib.Error: Aravis says why (unreachable, access denied, ...)
            raise DeviceError(f"cannot open genicam camera {self.name!r}: {exc}") from exc

    def _tune_gige(self, spec: DeviceSpec) -> None:
        """Packet size and socket buffer: the two settings that decide whether GVSP keeps up."""
        packet = spec.int_param("packet_size", 0)
        if packet:
            self._cam.gv_set_packet_size(packet)
        else:
            try:
                self._cam.gv_auto_packet_size()
            except Exception as exc:  # noqa: BLE001 - cameras without GevSCPSFireTestPacket: keep theirs
                log.debug("genicam %s: no auto packet size (%s); keeping %s", self.name, exc, packet)
        self._socket_buffer = spec.int_param("socket_buffer", 0)

    def _aravis_version(self) -> str:
        arv = self._arv
        try:
            return f"{arv.MAJOR_VERSION}.{arv.MINOR_VERSION}.{arv.MICRO_VERSION}"
        except AttributeError:
            return "0.8"

    # ------------------------------------------------------------------ properties
    def _probe_capabilities(self) -> frozenset[Capability]:
        """Asked once at open: colour only where the camera offers RGB8 or BayerRG8 (what rgb8
        and bayer_rg8 map to; configure() refuses the one it does not offer)."""
        caps = {
            Capability.HARDWARE_TRIGGER,
            Capability.FREE_RUN,
            Capability.FRAME_COUNTER,
            Capability.DEVICE_TIMESTAMPS,
            Capability.EXPOSURE_CONTROL,
        }
        if _COLOR_FORMATS & set(self._pixel_formats()):
            caps.add(Capability.COLOR)
        return frozenset(caps)

    def _pixel_formats(self) -> list[str]:
        try:
            return list(self._cam.dup_available_pixel_formats_as_strings())
        except Exception:  # noqa: BLE001 - older Aravis: no list, assume mono
            return ["Mono8"]

    @property
    def frame_shape(self) -> tuple[int, ...]:
        region = self._cam.get_region()
        h, w = int(region.height), int(region.width)
        return (h, w, 3) if self._cam.get_pixel_format_as_string() == "RGB8" else (h, w)

    @property
    def pixel_format(self) -> str:
        """The camera's current format (a BayerRG8 default is bayer_rg8, not mono8)."""
        fmt = _FORMAT_OF.get(self._cam.get_pixel_format_as_string() or "Mono8")
        return fmt if fmt is not None else super().pixel_format

    @property
    def frame_dtype(self) -> np.dtype[np.generic]:
        fmt = self._cam.get_pixel_format_as_string() or "Mono8"
        return np.dtype(np.uint16) if fmt.endswith(("10", "12", "16")) else np.dtype(np.uint8)

    # ------------------------------------------------------------------ settings
    def _do_configure(self, settings: CameraSettings) -> None:
        cam, dev = self._cam, self._dev
        try:
            if settings.pixel_format is not None:
                fmt = PIXEL_FORMATS[settings.pixel_format]
                if fmt not in self._pixel_formats():
                    raise ConfigError(
                        f"genicam camera {self.name!r}: pixel format {fmt} not offered "
                        f"({', '.join(self._pixel_formats())})"
                    )
                cam.set_pixel_format_from_string(fmt)
            lo, hi = cam.get_exposure_time_bounds()
            if not lo <= settings.exposure_us <= hi:
                raise ConfigError(
                    f"genicam camera {self.name!r}: exposure {settings.exposure_us} us outside {lo:g}..{hi:g}"
                )
            cam.set_exposure_time(float(settings.exposure_us))
            if cam.is_gain_available():
                glo, ghi = cam.get_gain_bounds()
                cam.set_gain(min(max(settings.gain_db, glo), ghi))
            elif settings.gain_db:
                raise ConfigError(f"genicam camera {self.name!r} has no gain control")
            if settings.trigger_mode == "hardware":
                dev.set_string_feature_value("TriggerSelector", "FrameStart")
                dev.set_string_feature_value("TriggerMode", "On")
                dev.set_string_feature_value("TriggerSource", self._trigger_source)
                dev.set_string_feature_value("TriggerActivation", self._activation)
            else:
                dev.set_string_feature_value("TriggerMode", "Off")
                if cam.is_frame_rate_available():
                    cam.set_frame_rate(settings.free_run_fps)
            cam.set_acquisition_mode(self._arv.AcquisitionMode.CONTINUOUS)
        except ConfigError:
            raise
        except Exception as exc:  # GLib.Error from a feature write
            raise ConfigError(f"genicam camera {self.name!r}: cannot apply {settings!r}: {exc}") from exc

    # ------------------------------------------------------------------ acquisition
    def _do_start(self) -> None:
        arv = self._arv
        try:
            stream = self._cam.create_stream(None, None)
            if self._cam.is_gv_device() and self._socket_buffer:
                stream.set_property("socket-buffer", arv.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", self._socket_buffer)
            payload = self._cam.get_payload()
            for _ in range(self._n_buffers):
                stream.push_buffer(arv.Buffer.new_allocate(payload))
            self._cam.start_acquisition()
        except Exception as exc:
            raise DeviceError(f"genicam camera {self.name!r}: cannot start acquisition: {exc}") from exc
        self._shape = self.frame_shape
        self._dtype = self.frame_dtype
        self._format = self.pixel_format
        self._stream = stream

    def _do_stop(self) -> None:
        try:
            self._cam.stop_acquisition()
        except Exception as exc:  # noqa: BLE001 - an unplugged camera cannot be stopped: report, go on
            log.warning("genicam camera %s: stop_acquisition failed: %s", self.name, exc)
        # The acquisition thread drains what the stream already completed: frames stay readable.

    def _grab(self, timeout_s: float) -> Frame | None:
        """The next completed buffer as a Frame; incomplete ones are counted and skipped."""
        stream = self._stream
        while True:
            if self._stopping:
                buf = stream.try_pop_buffer()
            else:
                buf = stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
            if buf is None:
                return None
            frame = self._take(buf)
            if frame is not None:
                return frame

    def _take(self, buf: Any) -> Frame | None:
        """A completed buffer as a Frame (None, counted, for an incomplete one); the buffer goes
        back to the stream's pool either way."""
        arv = self._arv
        host_ns = time.monotonic_ns()
        try:
            if buf.get_status() != arv.BufferStatus.SUCCESS:
                self._incomplete += 1
                log.warning(
                    "genicam camera %s: incomplete buffer (%s), re-queued", self.name, buf.get_status()
                )
                return None
            counter = self._unwrap(int(buf.get_frame_id()))
            if self._last_counter is not None and counter > self._last_counter + 1:
                self._counter_gaps += counter - self._last_counter - 1
            self._last_counter = counter
            data = np.frombuffer(buf.get_data(), dtype=self._dtype)
            image = data[: int(np.prod(self._shape))].reshape(self._shape).copy()
            t_ns = int(buf.get_timestamp()) or int(buf.get_system_timestamp())
            return Frame(
                image=image,
                t_exposure_start_us=t_ns // 1000,
                exposure_us=self._settings.exposure_us,
                frame_counter=counter,
                host_time_ns=host_ns,
                pixel_format=self._format,
            )
        finally:
            if self._stream is not None:
                self._stream.push_buffer(buf)

    def _unwrap(self, raw: int) -> int:
        """GigE Vision 1.x block ids are 16-bit and run 1..65535 (0 unused): extend them so the
        counter keeps increasing by one per frame across the wrap."""
        last = self._last_raw
        if last is not None and raw < last and last - raw > 1 << 15:
            self._wraps += 1
        self._last_raw = raw
        return raw + self._wraps * 0xFFFF if raw <= 0xFFFF else raw

    def _stream_stats(self) -> dict[str, int]:
        stream = self._stream
        if stream is None:
            return dict(self._final_stats)
        out: dict[str, int] = {}
        try:
            for i in range(stream.get_n_infos()):
                name = stream.get_info_name(i)
                if name in _STAT_NAMES:
                    out[name] = int(stream.get_info_uint64(i))
        except Exception as exc:  # noqa: BLE001 - statistics are diagnostics: never fail a take over them
            log.debug("genicam camera %s: stream statistics unavailable: %s", self.name, exc)
        return out

    def _counters(self) -> tuple[int, dict[str, int]]:
        extra = self._stream_stats()
        extra["incomplete_buffers"] = self._incomplete
        extra["frame_counter_gaps"] = self._counter_gaps
        return self._incomplete + self._counter_gaps, extra

    def software_trigger(self) -> None:
        """Fire TriggerSoftware (tests and bench use, with trigger_source=Software)."""
        self._check_open()
        self._dev.execute_command("TriggerSoftware")

    def _do_close(self) -> None:
        self._final_stats = self._stream_stats()
        self._stream = None
        self._cam = None
        self._dev = None


def open_genicam_camera(spec: DeviceSpec) -> GenicamCamera:
    """Factory for `genicam://SERIAL_OR_NAME[?trigger_source=Line0&...]` (see the module docstring)."""
    return GenicamCamera(spec)
