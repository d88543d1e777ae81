"""A stand-in for the part of Aravis (`gi.repository.Aravis`) the genicam:// backend uses.

One USB3 Vision camera with a buffer pool as Aravis has it: the host pushes buffers, the camera
fills one per trigger edge on its line (`line_pulse`), per TriggerSoftware, or at its frame
rate when TriggerMode is Off, and the host pops them. A filled buffer carries a block id from 1
and a device timestamp in ns; an edge with no free buffer is an underrun, counted.
"""

from __future__ import annotations

import collections
import threading
import time
import types
from typing import Any

BUFFER_SUCCESS = 0


class FakeBuffer:
    def __init__(self, size: int) -> None:
        self.data = bytearray(size)
        self.frame_id = 0
        self.timestamp_ns = 0

    def get_data(self) -> bytes:
        return bytes(self.data)

    def get_frame_id(self) -> int:
        return self.frame_id

    def get_status(self) -> int:
        return BUFFER_SUCCESS

    def get_timestamp(self) -> int:
        return self.timestamp_ns

    def get_system_timestamp(self) -> int:
        return self.timestamp_ns


class FakeStream:
    def __init__(self) -> None:
        self._free: collections.deque[FakeBuffer] = collections.deque()
        self._done: collections.deque[FakeBuffer] = collections.deque()
        self._cond = threading.Condition()
        self.infos = {"n_completed_buffers": 0, "n_underruns": 0, "n_failures": 0, "n_missing_packets": 0}

    def set_property(self, name: str, value: object) -> None: ...

    def push_buffer(self, buf: FakeBuffer) -> None:
        with self._cond:
            self._free.append(buf)

    def fill(self, frame_id: int, value: int) -> None:
        with self._cond:
            if not self._free:
                self.infos["n_underruns"] += 1
                return
            buf = self._free.popleft()
            buf.data[:] = bytes([value % 256]) * len(buf.data)
            buf.frame_id = frame_id
            buf.timestamp_ns = time.monotonic_ns()
            self._done.append(buf)
            self.infos["n_completed_buffers"] += 1
            self._cond.notify_all()

    def timeout_pop_buffer(self, timeout_us: int) -> FakeBuffer | None:
        with self._cond:
            self._cond.wait_for(lambda: bool(self._done), timeout=timeout_us / 1e6)
            return self._done.popleft() if self._done else None

    def try_pop_buffer(self) -> FakeBuffer | None:
        return self.timeout_pop_buffer(0)

    def get_n_infos(self) -> int:
        return len(self.infos)

    def get_info_name(self, i: int) -> str:
        return list(self.infos)[i]

    def get_info_uint64(self, i: int) -> int:
        return list(self.infos.values())[i]


class FakeCamera:
    def __init__(self, *, formats: tuple[str, ...] = ("Mono8",), width: int = 64, height: int = 48) -> None:
        self.formats = list(formats)
        self.pixel_format = formats[0]
        self.region = types.SimpleNamespace(x=0, y=0, width=width, height=height)
        self.features: dict[str, str] = {"TriggerMode": "Off"}
        self.exposure_us = 10_000.0
        self.fps = 30.0
        self.acquiring = False
        self._stream: FakeStream | None = None
        self._frame_id = 0
        self._free_run: threading.Thread | None = None

    # identity and settings
    def get_device(self) -> FakeCamera:
        return self

    def is_gv_device(self) -> bool:
        return False

    def get_vendor_name(self) -> str:
        return "rigd-test"

    def get_model_name(self) -> str:
        return "FakeAravisCamera"

    def get_device_serial_number(self) -> str:
        return "RIGD01"

    def dup_available_pixel_formats_as_strings(self) -> list[str]:
        return list(self.formats)

    def get_pixel_format_as_string(self) -> str:
        return self.pixel_format

    def set_pixel_format_from_string(self, fmt: str) -> None:
        self.pixel_format = fmt

    def get_region(self) -> Any:
        return self.region

    def set_region(self, x: int, y: int, w: int, h: int) -> None:
        self.region = types.SimpleNamespace(x=x, y=y, width=w, height=h)

    def get_exposure_time_bounds(self) -> tuple[float, float]:
        return 10.0, 1e6

    def set_exposure_time(self, us: float) -> None:
        self.exposure_us = us

    def is_gain_available(self) -> bool:
        return True

    def get_gain_bounds(self) -> tuple[float, float]:
        return 0.0, 24.0

    def set_gain(self, gain: float) -> None: ...

    def is_frame_rate_available(self) -> bool:
        return True

    def set_frame_rate(self, fps: float) -> None:
        self.fps = fps

    def set_acquisition_mode(self, mode: int) -> None: ...

    def set_string_feature_value(self, name: str, value: str) -> None:
        self.features[name] = value

    def execute_command(self, name: str) -> None:
        if name == "TriggerSoftware" and self.features.get("TriggerSource") == "Software":
            self._expose()

    # acquisition
    def create_stream(self, callback: object, data: object) -> FakeStream:
        self._stream = FakeStream()
        return self._stream

    def get_payload(self) -> int:
        channels = 3 if self.pixel_format == "RGB8" else 1
        return int(self.region.width * self.region.height * channels)

    def start_acquisition(self) -> None:
        self.acquiring = True
        if self.features.get("TriggerMode") == "Off":
            self._free_run = threading.Thread(target=self._run_free, daemon=True)
            self._free_run.start()

    def stop_acquisition(self) -> None:
        self.acquiring = False
        if self._free_run is not None:
            self._free_run.join()
            self._free_run = None

    def line_pulse(self) -> None:
        """A rising edge on the trigger line: exposes only when acquiring in trigger mode."""
        if self.features.get("TriggerMode") == "On" and self.features.get("TriggerSource") != "Software":
            self._expose()

    def _expose(self) -> None:
        if self.acquiring and self._stream is not None:
            self._frame_id += 1
            self._stream.fill(self._frame_id, self._frame_id)

    def _run_free(self) -> None:
        while self.acquiring:
            self._expose()
            time.sleep(1.0 / self.fps)


def fake_aravis(camera: FakeCamera) -> Any:
    """A module-like object in place of `gi.repository.Aravis`, whose only camera is `camera`."""
    return types.SimpleNamespace(
        MAJOR_VERSION=0,
        MINOR_VERSION=8,
        MICRO_VERSION=99,
        AcquisitionMode=types.SimpleNamespace(CONTINUOUS=1),
        BufferStatus=types.SimpleNamespace(SUCCESS=BUFFER_SUCCESS),
        GvStreamSocketBuffer=types.SimpleNamespace(FIXED=1),
        Buffer=types.SimpleNamespace(new_allocate=FakeBuffer),
        Camera=types.SimpleNamespace(new=lambda device_id: camera),
        update_device_list=lambda: None,
        get_n_devices=lambda: 1,
        get_device_id=lambda i: "rigd-test-FakeAravisCamera-RIGD01",
        get_device_serial_nbr=lambda i: "RIGD01",
    )
