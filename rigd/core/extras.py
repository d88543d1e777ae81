"""The optional libraries behind rigd's extras, and the one error that says which extra to install.

`pip install rigd` is what a training job needs to read takes (numpy, h5py, numba, pydantic).
The rig itself, the console, calibration and reconstruction pull heavier libraries (OpenCV,
dask, Starlette, ZeroMQ, ...), each behind an extra (pyproject.toml). Code that needs one
imports it through `require`, so a lean install fails with the extra to install, not a bare
ModuleNotFoundError from deep inside a call.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Final

from rigd.core.errors import MissingExtraError

#: Import name -> (distribution, the extra that installs it).
OPTIONAL: Final[dict[str, tuple[str, str]]] = {
    "cv2": ("opencv-contrib-python-headless", "frames"),
    "scipy": ("scipy", "calibration"),
    "yaml": ("PyYAML", "capture"),
    "serial": ("pyserial", "capture"),
    "usb": ("pyusb", "capture"),
    "hid": ("hidapi", "capture"),
    "zmq": ("pyzmq", "capture"),
    "prometheus_client": ("prometheus-client", "capture"),
    "dask": ("dask", "reconstruct"),
    "starlette": ("starlette", "console"),
    "uvicorn": ("uvicorn", "console"),
    "torch": ("torch", "torch"),
    "mcap": ("mcap", "ros"),
    "rosbags": ("rosbags", "ros"),
}


def missing_extra(module: str, why: str) -> MissingExtraError:
    """The error for an optional library that is not installed: what needed it and what to install."""
    top = module.split(".")[0]
    dist, extra = OPTIONAL.get(top, (top, "rig"))
    return MissingExtraError(
        f"{why} needs {dist}, which this install lacks: pip install 'rigd[{extra}]' "
        "(or 'rigd[rig]' for everything the rig runs)"
    )


def require(module: str, why: str) -> ModuleType:
    """Import an optional library, or raise MissingExtraError naming `why` and the extra."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name is not None and exc.name.split(".")[0] == module.split(".")[0]:
            raise missing_extra(module, why) from exc
        raise
