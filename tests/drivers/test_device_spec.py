"""Device specs: a parameter given twice is refused for every backend, not only the simulator's
(which of two values would win is the parser's accident)."""

from __future__ import annotations

import pytest

from drivers.registry import DeviceSpec
from rigd.core.errors import ConfigError


@pytest.mark.parametrize(
    ("raw", "repeated"),
    [
        ("serial:///dev/ttyUSB0?baud=115200&baud=9600", ("baud",)),
        ("file:///tmp/rec.raw?pace=1&loop=1&pace=2&loop=0", ("loop", "pace")),
        ("genicam://cam?exposure=1&exposure=", ("exposure",)),
    ],
)
def test_a_repeated_parameter_is_refused_naming_it(raw: str, repeated: tuple[str, ...]) -> None:
    spec = DeviceSpec.parse(raw)
    assert spec.repeated == repeated
    with pytest.raises(ConfigError, match="given more than once: " + ", ".join(repeated)):
        spec.check_params({"baud", "pace", "loop", "exposure"})


def test_parameters_given_once_pass() -> None:
    spec = DeviceSpec.parse("file:///tmp/rec.raw?pace=1&loop=1")
    assert spec.repeated == ()
    spec.check_params({"pace", "loop"})
    assert spec.params == {"pace": "1", "loop": "1"}
