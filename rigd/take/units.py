"""Self-describing datasets for generic HDF5 users: `units` on every time and length dataset, and
the compression filter named where a plain h5py or h5dump user would meet the missing-plugin error.

A take is read by tools that know nothing of rigd (h5py alone, h5dump, HDFView, MATLAB). Two things
they cannot guess: what unit a number is in (rig or device microseconds, host nanoseconds, pixels,
metres), and why a dataset will not read ("can't open ... filter 32015"): the `compression_filter`
attribute names the filter and how to get it. `label` is called where datasets are created;
`label_tree` once at finalize catches the rest (scalars, calibration, sync).
"""

from __future__ import annotations

from typing import Final

import h5py

#: units by dataset name (time: us or ns; length: px, m).
UNITS: Final[dict[str, str]] = {
    "t": "us",
    "t_us": "us",
    "t_device": "us",
    "t_offset": "us",
    "t_exposure_start_us": "us",
    "t_exposure_start_device_us": "us",
    "exposure_us": "us",
    "host_time_ns": "ns",
    "x": "px",
    "y": "px",
    "tail_t": "us",
    "tail_x": "px",
    "tail_y": "px",
    "image_size": "px",
    "K": "px",
}
#: The same names under /calibration mean other things.
CALIBRATION_UNITS: Final[dict[str, str]] = {"t": "m", "K": "px", "image_size": "px", "R": "1", "dist": "1"}
#: Registered HDF5 filter ids of the codecs rigd writes, and what a plain user needs for them.
_PLUGIN = (
    "needs the HDF5 plugin: in Python `import hdf5plugin` before h5py reads it; for h5dump, HDFView "
    "or MATLAB set HDF5_PLUGIN_PATH to hdf5plugin.PLUGIN_PATH (pip install hdf5plugin)"
)
FILTERS: Final[dict[int, str]] = {
    32015: f"Zstd (HDF5 filter 32015) {_PLUGIN}",
    32004: f"LZ4 (HDF5 filter 32004) {_PLUGIN}",
    32001: f"Blosc (HDF5 filter 32001) {_PLUGIN}",
}
UNITS_ATTR: Final = "units"
FILTER_ATTR: Final = "compression_filter"


def label(ds: h5py.Dataset) -> h5py.Dataset:
    """Set `units` (when the dataset's name has one) and `compression_filter` (when a plugin
    filter compresses it) on one dataset; returns it."""
    name = ds.name.rsplit("/", 1)[-1]
    table = CALIBRATION_UNITS if ds.name.startswith("/calibration/") else UNITS
    unit = table.get(name)
    if unit is not None and UNITS_ATTR not in ds.attrs:
        ds.attrs[UNITS_ATTR] = unit
    plist = ds.id.get_create_plist()
    for i in range(plist.get_nfilters()):
        code = int(plist.get_filter(i)[0])
        if code in FILTERS:
            ds.attrs[FILTER_ATTR] = FILTERS[code]
    return ds


def label_tree(f: h5py.File | h5py.Group) -> None:
    """`label` every dataset under `f`."""

    def visit(_name: str, obj: object) -> None:
        if isinstance(obj, h5py.Dataset):
            label(obj)

    f.visititems(visit)
