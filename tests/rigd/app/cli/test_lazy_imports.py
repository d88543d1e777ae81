"""The command line starts without the heavy libraries: each command imports what it needs when
it runs, so `rigd --help` and `rigd status` do not wait seconds for numba, h5py or OpenCV.

Checked in a fresh interpreter (this test process has long imported everything), by what is in
`sys.modules`, never by a time.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

HEAVY = ("numba", "h5py", "cv2", "dask", "starlette", "uvicorn", "zmq", "torch", "scipy")


def _loaded_after(code: str) -> list[str]:
    probe = f"{code}\nimport json, sys\nprint(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return list(json.loads(done.stdout.strip().splitlines()[-1]))


@pytest.mark.slow
def test_importing_the_cli_loads_no_heavy_library() -> None:
    assert _loaded_after("import rigd.app.cli") == []


@pytest.mark.slow
def test_help_of_every_command_loads_no_heavy_library() -> None:
    code = (
        "import sys\nfrom typer.testing import CliRunner\nfrom rigd.app.cli import app\n"
        "r = CliRunner()\n"
        "for args in (['--help'], ['capture', '--help'], ['calibrate', 'events', '--help'],\n"
        "             ['calibrate', 'guided', '--help'], ['export', '--help'], ['reconstruct', '--help'],\n"
        "             ['simulate-events', '--help'], ['recover', '--help'], ['takes', '--help']):\n"
        "    res = r.invoke(app, args)\n"
        "    assert res.exit_code == 0, (args, res.output)\n"
    )
    assert _loaded_after(code) == []


def test_spelled_out_choices_match_the_libraries() -> None:
    """The choices the help lists without importing a library are the library's own."""
    from calibration.e2calib import METHODS
    from rigd.app.commands.calibrate import E2CALIB_METHODS
    from rigd.app.commands.export import EXPORT_FORMATS, EXPORT_SPLITS, EXPORT_WORLDS
    from rigd.app.commands.reconstruct import LOCAL_SCHEDULER_NAMES
    from rigd.products.export import FORMATS, SPLITS, WORLDS
    from rigd.products.reconstruct_scheduler import LOCAL_SCHEDULERS

    assert E2CALIB_METHODS == METHODS
    assert EXPORT_FORMATS == FORMATS
    assert EXPORT_WORLDS == WORLDS
    assert EXPORT_SPLITS == SPLITS
    assert LOCAL_SCHEDULER_NAMES == LOCAL_SCHEDULERS


def test_core_exports_load_on_first_use() -> None:
    code = "import rigd.core.errors\nimport sys\nassert 'numpy' not in sys.modules, 'numpy loaded'"
    assert _loaded_after(code) == []
    import rigd.core

    assert rigd.core.ClockMap.__module__ == "rigd.core.timebase"
    assert json.dumps(sorted(rigd.core.__all__))  # every name in __all__ resolves
    for name in rigd.core.__all__:
        getattr(rigd.core, name)


@pytest.mark.slow
def test_status_path_loads_no_numpy() -> None:
    """`rigd status` needs the protocol client and its models, not numpy (0.2 s of a 1 s start)."""
    code = (
        "import rigd.app.service.client, rigd.app.service.protocol, rigd.app.commands.service\n"
        "import sys\nassert 'numpy' not in sys.modules, 'numpy loaded'"
    )
    assert "h5py" not in _loaded_after(code)
