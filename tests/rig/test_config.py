from __future__ import annotations

import pytest

from rig.config import ConfigError, load_config, parse_config
from tests.conftest import REPO

MINIMAL = {"cameras": [{"id": "cam0", "driver": "pattern"}]}


def test_example_config_loads_with_every_section():
    cfg = load_config(REPO / "deploy" / "rig.example.toml")
    assert cfg.rig_id == "line-3" and [c.id for c in cfg.cameras] == ["cam00", "cam01"]
    cam = cfg.cameras[0]
    assert (cam.driver, cam.device, cam.settings.width, cam.settings.sync, cam.settings.locked) == (
        "oak",
        "18443010D1C2A41200",
        1280,
        "fsin",
        True,
    )
    assert (cfg.trigger.kind, cfg.trigger.arbitration_id, cfg.trigger.min_interval_ms) == ("serial", 0x181, 250.0)
    assert cfg.thresholds.sync_tolerance_ns == 2_000_000 and cfg.storage.min_free_gb == 5.0
    assert str(cfg.storage.spill) == "/var/spool/cadsplat/spill"


def test_defaults_and_relative_paths(tmp_path):
    cfg = parse_config({**MINIMAL, "storage": {"root": "caps"}}, base=tmp_path)
    assert cfg.storage.root == tmp_path / "caps" and cfg.trigger.kind == "software" and cfg.calibration is None
    assert cfg.registration == {}  # read by reconstruction.registration.RegistrationConfig.from_dict, which holds the defaults
    assert cfg.storage.spill is None  # rig.store.default_spill_dir(), chosen where the store is opened
    assert parse_config({**MINIMAL, "storage": {"spill": "../spill"}}, base=tmp_path).storage.spill == tmp_path / "../spill"


def test_registration_table_is_kept_as_written():
    cfg = parse_config({**MINIMAL, "registration": {"known_part": "bracket_v3", "scale_tolerance": 0.05}})
    assert cfg.registration == {"known_part": "bracket_v3", "scale_tolerance": 0.05}


def test_simulation_table_is_kept_as_written():
    # Its up goes into every capture when the calibration measured none (simulation.up.capture_up).
    assert parse_config({**MINIMAL, "simulation": {"up": [0, 0, 1], "material": "steel"}}).simulation == {
        "up": [0, 0, 1],
        "material": "steel",
    }
    assert parse_config(MINIMAL).simulation == {}


@pytest.mark.parametrize(
    "doc, message",
    [
        ({}, "cameras must be a non-empty array"),
        ({"cameras": [{"driver": "pattern"}]}, "cameras[0].id is required"),
        ({"cameras": [{"id": "a", "driver": "pattern"}, {"id": "a", "driver": "pattern"}]}, "'a' appears twice"),
        ({"cameras": [{"id": "a", "driver": "gopro"}]}, "cameras[0].driver must be one of oak, replay, pattern"),
        ({"cameras": [{"id": "a", "driver": "pattern", "width": -5}]}, "cameras[0].width must be an integer in [16, 8192], got -5"),
        ({"cameras": [{"id": "a"}]}, "cameras[0].device is required for an OAK camera"),
        ({"cameras": [{"id": "a", "driver": "pattern", "sync": "fsin"}]}, "cameras[0].sync = 'fsin' needs exposure_us"),
        ({"cameras": [{"id": "a", "driver": "pattern", "exposre_us": 5}]}, "unknown key cameras[0].exposre_us"),
        ({**MINIMAL, "trigger": {"kind": "serial"}}, "trigger.port is required"),
        ({**MINIMAL, "trigger": {"kind": "usb"}}, "trigger.kind must be one of serial, can, software"),
        ({**MINIMAL, "trigger": {"pattern": "GO"}}, "trigger.pattern needs a named group"),
        ({**MINIMAL, "trigger": {"payload_format": "<QQ"}}, "a CAN frame holds 8"),
        ({**MINIMAL, "storage": {"min_free_gb": "lots"}}, "storage.min_free_gb must be a number"),
        ({**MINIMAL, "storage": {"root": "/data/caps", "spill": "/data/caps/spill"}}, "storage.spill must lie outside storage.root"),
        ({**MINIMAL, "thresholds": {"black_level": 2}}, "thresholds.black_level must be a number in [0, 1]"),
        ({**MINIMAL, "extra": 1}, "unknown key extra"),
        ({**MINIMAL, "registration": 3}, "registration must be a table"),
    ],
)
def test_errors_name_the_key(doc, message):
    with pytest.raises(ConfigError) as e:
        parse_config(doc)
    assert message in str(e.value) and str(e.value).startswith("rig.toml: ")


def test_unreadable_files_are_one_sentence(tmp_path):
    with pytest.raises(ConfigError, match="no such rig config file"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("cameras = [[[")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)


def test_the_image_pixel_cap_is_a_limit_of_the_rig():
    """Issue 58 (9): [limits] max_image_pixels, 50 MP unless set, never below the rig's own frames."""
    assert parse_config(MINIMAL).max_image_pixels == 50_000_000
    assert parse_config({**MINIMAL, "limits": {"max_image_pixels": 20_000_000}}).max_image_pixels == 20_000_000
    big = {"cameras": [{"id": "cam0", "driver": "pattern", "width": 8000, "height": 6000}]}
    with pytest.raises(ConfigError, match=r"limits\.max_image_pixels \(20000000\) is below cameras\[0\]'s 8000x6000 frames"):
        parse_config({**big, "limits": {"max_image_pixels": 20_000_000}})
    with pytest.raises(ConfigError, match=r"limits\.max_image_pixels must be an integer in \[1000000, 150000000\]"):
        parse_config({**MINIMAL, "limits": {"max_image_pixels": 10**9}})
