"""calibration.json states its scale: a board calibration is metric (`units: m`), an SfM one is not."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.calibfile import (
    CalibrationDoc,
    CalibrationFileError,
    CalibrationStore,
    read_calibration,
)
from calibration.camera import Camera


def cams() -> dict[str, Camera]:
    k = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    return {"cam0": Camera(k, 64, 48, np.zeros(0), np.eye(4))}


def test_board_calibration_says_metric_and_sfm_says_unknown(tmp_path):
    board = CalibrationStore(tmp_path / "board.json").commit(CalibrationDoc(cams(), source="board"))
    doc = json.loads((tmp_path / "board.json").read_text())
    assert board.units == "m" and doc["units"] == "m" and doc["scale"].startswith("metric")
    # A drift correction keeps the frame, so it keeps the units.
    assert board.with_cameras(cams(), source="drift-correction").units == "m"

    CalibrationStore(tmp_path / "sfm.json").commit(CalibrationDoc(cams(), source="sfm"))
    doc = json.loads((tmp_path / "sfm.json").read_text())
    assert "units" not in doc and doc["scale"].startswith("unknown")
    assert read_calibration(tmp_path / "sfm.json").units is None


def test_a_calibration_in_units_it_does_not_know_is_refused_where_it_is_loaded(tmp_path):
    CalibrationStore(tmp_path / "c.json").commit(CalibrationDoc(cams(), source="board"))
    doc = json.loads((tmp_path / "c.json").read_text())
    for bad in ("meters", ["m"]):
        (tmp_path / "c.json").write_text(json.dumps({**doc, "units": bad}))
        with pytest.raises(CalibrationFileError) as e:
            read_calibration(tmp_path / "c.json")
        assert str(e.value).startswith(f"{tmp_path / 'c.json'}: units {bad!r} is not a unit cadsplat knows (one of m, mm, cm, in")
    (tmp_path / "c.json").write_text(json.dumps({**doc, "units": "mm"}))
    assert read_calibration(tmp_path / "c.json").units == "mm"
