"""Default parameters of the navigation law, in one place.

:class:`confnav.navigation.control.Controller`, ``confnav simulate``, the ``Goal`` message
(``schemas/messages.py``), the controller service and ``confnav demo`` all read them from here,
so a robot driven through the services gets exactly the library's defaults. Units: metres and
seconds. No imports: the schemas load this module.
"""

from __future__ import annotations

from typing import Final, Literal

SpeedLaw = Literal["normalized", "theorem2"]

#: Navigation function by name (``"harmonic"``: tuning-free; ``"kr"``: Koditschek-Rimon).
NAVFN: Final = "harmonic"
#: ``"normalized"``: unit direction of the Theorem 2 field times ``min(v_max, gain * dist)``;
#: ``"theorem2"``: the plain law ``-gain conj(T') grad phi`` saturated at ``v_max``.
SPEED_LAW: Final[SpeedLaw] = "normalized"
SPEED_LAWS: Final = ("normalized", "theorem2")
#: 1/s for the normalized law (speed = gain * distance to the goal near it); K for theorem2.
GAIN: Final = 1.0
#: Speed limit, m/s.
V_MAX: Final = 0.5
#: Arrival radius, m.
GOAL_TOL: Final = 0.02
#: Clearance (m) below which the normalized law slows down in proportion (0: off).
SLOW_DISTANCE: Final = 0.0
#: How long (s) a robot may keep applying one command after the pose it answers: the
#: simulator's ``max_cmd_age`` (docs/SERVICES.md). The law caps the speed so that a command
#: held this long moves the robot at most ``HOLD_FRACTION`` of its clearance (0: off).
HOLD_TIME: Final = 0.25
#: Fraction of the clearance a held command may use up (< 1 leaves the rest as margin).
HOLD_FRACTION: Final = 0.5
