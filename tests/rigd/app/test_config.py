"""Rig config loading and the shipped example configs."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.registry import DeviceSpec
from rigd.app.config import RigConfig, default_sim_rig
from rigd.core.errors import ConfigError

DEPLOY = Path(__file__).resolve().parents[3] / "deploy" / "configs"


def _params(spec: str) -> dict[str, float]:
    return {k: float(v) for k, v in DeviceSpec.parse(spec).params.items()}


def test_shipped_sim_config_is_the_built_in_rig() -> None:
    shipped = RigConfig.load(DEPLOY / "sim-rig.toml")
    built_in = default_sim_rig()
    assert shipped.trigger.settings == built_in.trigger.settings
    assert _params(shipped.trigger.spec) == _params(built_in.trigger.spec)
    for a, b in zip(
        shipped.cameras + shipped.event_sensors, built_in.cameras + built_in.event_sensors, strict=True
    ):
        assert a.name == b.name
        assert a.settings == b.settings
        assert _params(a.spec) == _params(b.spec)


def test_errors_name_file_and_field(tmp_path: Path) -> None:
    p = tmp_path / "rig.toml"
    p.write_text('[trigger]\nspec = "/dev/ttyACM0"\n[[cameras]]\nname = "9bad"\nspec = "sim://x/c"\n')
    with pytest.raises(ConfigError) as err:
        RigConfig.load(p)
    assert str(p) in str(err.value)
    assert "cameras.0.name" in str(err.value)


@pytest.mark.parametrize(
    ("name", "text", "match"),
    [
        ("rig.toml", "[trigger\n", "not valid TOML"),
        ("rig.json", "{", "not valid JSON"),
        ("rig.yaml", "a: [", "not valid YAML"),
        ("rig.ini", "", "unknown extension"),
    ],
)
def test_unparsable_files(tmp_path: Path, name: str, text: str, match: str) -> None:
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(ConfigError, match=match):
        RigConfig.load(p)


def test_duplicate_names_and_missing_file(tmp_path: Path) -> None:
    cfg = default_sim_rig().model_dump()
    cfg["event_sensors"][0]["name"] = "cam0"
    with pytest.raises(ConfigError, match="repeated: cam0"):
        RigConfig.from_data(cfg)
    with pytest.raises(ConfigError, match="cannot read rig config"):
        RigConfig.load(tmp_path / "nope.toml")


def test_spec_parameters_are_checked() -> None:
    spec = DeviceSpec.parse("sim://w/cam0?drift_ppm=abc&typo=1")
    with pytest.raises(ConfigError, match="drift_ppm='abc' is not a number"):
        spec.float_param("drift_ppm", 0.0)
    with pytest.raises(ConfigError, match="unknown parameter"):
        spec.check_params({"drift_ppm"})
    assert DeviceSpec.parse("/dev/ttyACM0").scheme == "serial"


def test_example_configs_load() -> None:
    """The configs shipped in deploy/ stay valid as the schema changes."""
    from pathlib import Path

    from rigd.app.config import RigConfig

    root = Path(__file__).resolve().parents[3] / "deploy" / "configs"
    configs = sorted(root.glob("*.toml"))
    assert len(configs) >= 2
    for path in configs:
        cfg = RigConfig.load(path)
        assert cfg.cameras or cfg.event_sensors


@pytest.mark.parametrize("suffix", [".toml", ".json", ".yaml"])
@pytest.mark.parametrize(
    "blob",
    [
        b"\xff\xfe\x00t\x00o",
        b"name = 'rig'\n\x80\x81\n",
        bytes(range(256)),
        b"\x89PNG\r\n\x1a\n" + b"\0" * 64,
    ],
)
def test_binary_or_non_utf8_config_is_one_line_naming_the_file(
    tmp_path: Path, suffix: str, blob: bytes
) -> None:
    path = tmp_path / f"b{suffix}"
    path.write_bytes(blob)
    with pytest.raises(ConfigError) as err:
        RigConfig.load(path)
    msg = str(err.value)
    assert str(path) in msg
    assert "\n" not in msg
    assert "not a text file" in msg or "not valid" in msg
