"""The rig-to-object scale a registration may take.

The library is metric. On a metric rig (`rig_metres_per_unit` known, from the capture's `units`) the
scale is a measurement: candidates and refinement stay within the part's size tolerance
(`scale_band`), a wrong-size look-alike loses, and the result states the measured size deviation.
Otherwise the scale comes from the data, anywhere in SCALE_SEARCH, and a look-alike at another size
is a tie.
"""

from __future__ import annotations

from calibration.sim3 import Sim3
from reconstruction.registration.result import SCALE_SEARCH, RegistrationError

# Default tolerance of a part's size against its CAD model on a metric rig (a fraction of its size).
SCALE_TOLERANCE = 0.10


def scale_band(rig_metres_per_unit: float | None, tolerance: float = SCALE_TOLERANCE) -> tuple[float, float]:
    """Allowed rig-to-object scales (the library is in metres).

    Metric rig (`rig_metres_per_unit` known): the part may differ from its CAD model by
    ±`tolerance` in size, so s = metres per rig unit / size ratio lies in
    [m / (1 + tol), m / (1 - tol)]. Unknown scale: SCALE_SEARCH, any scale a calibration can have.
    """
    if rig_metres_per_unit is None:
        return SCALE_SEARCH
    if not 0.0 <= tolerance < 1.0:
        raise RegistrationError(f"the scale tolerance must be in [0, 1), got {tolerance}")
    m = float(rig_metres_per_unit)
    return m / (1.0 + tolerance), m / (1.0 - tolerance)


def in_band(sim3: Sim3, band: tuple[float, float]) -> bool:
    return band[0] * (1 - 1e-9) <= sim3.scale <= band[1] * (1 + 1e-9)
