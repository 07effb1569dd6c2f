"""RegistrationConfig: rig.toml's [registration] table, its one copy of defaults, and its document."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.registration import SCALE_TOLERANCE, RegistrationConfig, RegistrationError
from rig.config import parse_config


def test_an_absent_table_takes_the_defaults():
    cfg = parse_config({"cameras": [{"id": "a", "driver": "pattern"}]})
    assert RegistrationConfig.from_dict(cfg.registration) == RegistrationConfig()
    assert RegistrationConfig().known_part is None and RegistrationConfig().scale_tolerance == SCALE_TOLERANCE


def test_rig_toml_table_and_document_round_trip():
    prior = Sim3(0.5, axis_angle_to_matrix(np.array([0.1, 0.2, 0.3])), np.array([0.1, 0.0, -0.2]))
    table = {"known_part": "bracket_v3", "scale_tolerance": 0.05, "photo_tie_break": False, "prior": prior.to_dict()}
    cfg = RegistrationConfig.from_dict(parse_config({"cameras": [{"id": "a", "driver": "pattern"}], "registration": table}).registration)
    assert (cfg.known_part, cfg.scale_tolerance, cfg.photo_tie_break) == ("bracket_v3", 0.05, False)
    np.testing.assert_allclose(cfg.prior.matrix(), prior.matrix())
    again = RegistrationConfig.from_dict(cfg.to_dict())
    assert {**again.to_dict(), "prior": None} == {**cfg.to_dict(), "prior": None}
    np.testing.assert_allclose(again.prior.matrix(), prior.matrix(), atol=1e-12)


@pytest.mark.parametrize(
    "table, message",
    [
        ({"scale_tolerance": 1.5}, "registration.scale_tolerance must be a number in [0, 0.99], got 1.5"),
        ({"known_part": 3}, "registration.known_part must be a library model id"),
        ({"photo_tie_break": "yes"}, "registration.photo_tie_break must be true or false"),
        ({"top_k": 0}, "registration.top_k must be an integer in [1, 10000]"),
        ({"known_prt": "x"}, "unknown key registration.known_prt"),
        ({"known_part": "x", "prior": {"scale": 1.0}}, "registration.prior must be a Sim(3) table"),
        ({"prior": Sim3.identity().to_dict()}, "a registration prior needs the known part"),
    ],
)
def test_errors_name_the_key(table, message):
    with pytest.raises(RegistrationError) as e:
        RegistrationConfig.from_dict(table)
    assert message in str(e.value)
