"""rig.toml keys for OAK cameras."""

from __future__ import annotations

import pytest

from rig.assembly import build_camera
from rig.config import ConfigError, parse_config

OAK = {
    "id": "cam0",
    "driver": "oak",
    "device": "18443010D1C2A41200",
    "socket": "CAM_B",
    "sync": "fsin",
    "exposure_us": 4000,
    "iso": 200,
    "white_balance_k": 5600,
}


def test_fsin_discard_reaches_the_driver():
    cfg = parse_config({"cameras": [{**OAK, "fsin_discard": 2}]})
    assert cfg.cameras[0].fsin_discard == 2
    drv = build_camera(cfg.cameras[0], None, 0, 1)
    assert (drv.socket, drv.fsin_discard) == ("CAM_B", 2)


@pytest.mark.parametrize(
    "cam, message",
    [
        ({**OAK, "fsin_discard": 9}, "rig.toml: cameras[0].fsin_discard must be an integer in [0, 8], got 9"),
        (
            {**OAK, "sync": "software", "fsin_discard": 1},
            "rig.toml: cameras[0].fsin_discard only applies to an OAK camera with sync = 'fsin'",
        ),
    ],
)
def test_fsin_discard_errors_name_the_key(cam, message):
    with pytest.raises(ConfigError) as e:
        parse_config({"cameras": [cam]})
    assert str(e.value) == message
