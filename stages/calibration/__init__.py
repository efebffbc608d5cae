"""Calibration: density test (DNL, INL, LSB, Nmin/Nmax/Nth/PDM), LSB against light, delay.

One idea a room, every name importable from ``stages.calibration`` as before:

- :mod:`.reset_peak`: where tau = T falls on the code axis (the LSB), the cycles at risk;
- :mod:`.second_stage`: Nmin/Nmax/Nth/PDM (eq. 3.4), one capture or a campaign;
- :mod:`.density`: the density test (sections 3.2, 5.1): widths, DNL, INL, LSB;
- :mod:`.tracking`: the LSB measured online from a range capture's background;
- :mod:`.lsb_light`: LSB against light (eq. 5.1);
- :mod:`.timescale`: code to time at a capture's light, delay and distance (eqs. 5.3, 5.4);
- :mod:`.plan`: the density tests to take, planned from the zero-distance capture.

Setting a name here (a test's ``monkeypatch.setattr(cal, "TRACK_MAX_SIGMA_PS", 1.0)``)
sets it in the room that uses it too, as it did when this was one module.
"""

import sys
import types

from stages.calibration import (  # the rooms themselves, for _Rooms
    density,
    lsb_light,
    plan,
    reset_peak,
    second_stage,
    timescale,
    tracking,
)
from stages.calibration.density import (  # noqa: F401
    DEAD_LIT,
    DEAD_LL,
    DEAD_XT_CODES,
    INL_RMS_FACTOR,
    LOCAL_CODES,
    OWN_CLEAR_LSB,
    OWN_TOP,
    PHASE_MIN_SHARE,
    PHASE_PULL,
    RESET_PLAUSIBLE,
    DensityResult,
    _coates_var,
    _dead_widths,
    _one_tdc,
    _own_top_widths,
    _refill,
    _x_of,
    cycles_needed,
    dead_codes,
    density_test,
    fill_from,
    implausible_reset_peak,
    light_stop,
    phase_depleted,
    width_variance,
)
from stages.calibration.lsb_light import (  # noqa: F401
    LsbFit,
    RowSplines,
    _spline_rows,
    fit_lsb,
    point_sigma_ps,
)
from stages.calibration.plan import (  # noqa: F401
    DEFAULT_LEVELS,
    Plan,
    plan_tests,
    zero_geometry,
)
from stages.calibration.reset_peak import (  # noqa: F401
    EDGE_MARGIN,
    RESET_HALF,
    at_risk_by_code,
    fit_reset_peak,
)
from stages.calibration.second_stage import (  # noqa: F401
    SecondStage,
    SecondStageAccumulator,
    campaign_second_stage,
    second_stage_params,
)
from stages.calibration.timescale import (  # noqa: F401
    CONTINUE_CODES,
    LSB_SPREAD_FLOOR_PS,
    LSB_SPREAD_SIGMAS,
    RESET_CLEARANCE,
    RESET_SEARCH,
    ScaleSplines,
    _bound_at,
    _identity,
    _interpolates,
    code_bounds,
    continue_table,
    delay_s,
    density_rows,
    distance_m,
    histogram_sigma_s,
    light_end,
    light_level,
    scale_at_light,
    scale_in_situ,
    scale_points,
    scale_refs,
    scale_splines,
    scale_spread,
    scale_unresolved,
)
from stages.calibration.tracking import (  # noqa: F401
    TRACK_MAX_REL,
    TRACK_MAX_SIGMA_PS,
    Tracking,
    signal_codes,
    track_lsb,
)


class _Rooms(types.ModuleType):
    """The package's module type: an attribute set on the package is set in every room that
    holds that name, so the rooms read it as one module's globals did."""

    def __setattr__(self, name, value):
        for room in (reset_peak, second_stage, density, tracking, lsb_light, timescale, plan):
            if name in vars(room):
                setattr(room, name, value)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Rooms
