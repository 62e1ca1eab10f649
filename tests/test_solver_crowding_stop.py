"""A map that no finer mesh can make usable stops refining with a CrowdingError (issue 23
item 3, issue 24 item 4): the smooth-grid cap does not grow with the nodes per side."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from confnav.conformal.solver import _check_resolvable
from confnav.errors import CrowdingError


def _level(tail: float) -> SimpleNamespace:
    return SimpleNamespace(resolution_error=tail, radii=np.array([0.3, 2e-5]))


def test_two_capped_levels_above_max_error_raise_crowding() -> None:
    with pytest.raises(CrowdingError, match=r"1\.3e-01 at 54 nodes.*radius 2\.0e-05.*atlas"):
        _check_resolvable(_level(0.13), 54, 0.13, 1e-4)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("tail", "prev", "max_error"),
    [
        (0.13, 0.0, 1e-4),  # first capped level: one more level may still lift it
        (0.05, 0.13, 1e-4),  # the tail more than halved: refining helps
        (1e-5, 1e-5, 1e-4),  # capped but within what the caller accepts
        (0.0, 0.0, 1e-4),  # not capped
    ],
)
def test_levels_that_may_still_help_go_on(tail: float, prev: float, max_error: float) -> None:
    _check_resolvable(_level(tail), 54, prev, max_error)  # type: ignore[arg-type]


def test_the_transform_worker_sends_a_map_that_crowds_to_the_atlas() -> None:
    """The transform service's worker measures crowding on the solved map too (the barred room
    of tests/test_cli_simulate.py, shrunk by 0.1 m: accurate to its tol, crowded by 10^6.6)."""
    from confnav.services.atlas_transform import single_or_atlas

    from confnav.geometry import Workspace
    from confnav.maps.footprint import inflate

    outer = [(-0.7, -0.7), (0.7, -0.7), (0.7, 0.7), (-0.7, 0.7)]
    bar = [(-0.65, -0.025), (0.42, -0.025), (0.42, 0.025), (-0.65, 0.025)]
    shrunk = inflate(Workspace(outer, [bar]), 0.1)
    out = single_or_atlas(shrunk, 1e-6)
    assert out.keys() == {"needs_atlas"}
    assert "one map crowds: the outer boundary crowded by 10^" in out["needs_atlas"]
    assert "coefficients" in single_or_atlas(Workspace(outer, [bar]), 1e-3, max_error=1e-2)
