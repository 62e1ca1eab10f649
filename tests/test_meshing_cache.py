"""plan_boundaries remembers the per-boundary feature distances of a workspace geometry: the
plans of every level are the ones computed from scratch, and another geometry is not served
from the memory."""

from __future__ import annotations

import numpy as np

from confnav.conformal import meshing
from confnav.scenes.workspaces import default_workspace, mirror_squares


def _same(a: list[meshing.PanelPlan], b: list[meshing.PanelPlan]) -> bool:
    return all(
        np.array_equal(p.nodes, q.nodes) and np.array_equal(p.vertices, q.vertices)
        for p, q in zip(a, b, strict=True)
    ) and len(a) == len(b)


def test_remembered_plans_equal_fresh_ones() -> None:
    ws = default_workspace()
    meshing._FEATURE_CACHE.clear()
    first = {lv: meshing.plan_boundaries(ws, lv, 1e-8) for lv in (36, 80, 180)}
    assert meshing._FEATURE_CACHE  # remembered
    for lv, plans in first.items():
        meshing._FEATURE_CACHE.clear()
        assert _same(plans, meshing.plan_boundaries(ws, lv, 1e-8))


def test_another_geometry_is_computed_afresh() -> None:
    """Two gaps: different node counts on the facing sides, each as computed alone."""
    meshing._FEATURE_CACHE.clear()
    wide = meshing.plan_boundaries(mirror_squares(0.1), 54, 1e-8)
    narrow = meshing.plan_boundaries(mirror_squares(0.01), 54, 1e-8)
    meshing._FEATURE_CACHE.clear()
    alone = meshing.plan_boundaries(mirror_squares(0.01), 54, 1e-8)
    assert _same(narrow, alone)
    assert not _same(wide, narrow)


def test_pruned_features_give_the_distances_of_all_features() -> None:
    """Features bounded away by their boxes (meshing._nearest_features) change no distance
    and no nearest feature: bit for bit the values of the distances to every feature, on a
    workspace where most features are pruned (50 obstacles) and on two with few features."""
    import shapely

    from confnav.scenes.workspaces import mixed_obstacles

    frac, _ = meshing._sample_taus()
    for ws in (mixed_obstacles(50, seed=0), mirror_squares(0.01), default_workspace()):
        rings = [shapely.LinearRing(np.column_stack([z.real, z.imag])) for z in ws.boundaries]
        anchor = shapely.Point(ws.anchor.real, ws.anchor.imag)
        for j, z in enumerate(ws.boundaries):
            feats = [anchor, *(r for i, r in enumerate(rings) if i != j)]
            fast = meshing._feature_distance(z, feats, frac)
            old = meshing.NEAR_FEATURES_FIRST
            meshing.NEAR_FEATURES_FIRST = len(feats)  # every feature's exact distance
            try:
                full = meshing._feature_distance(z, feats, frac)
            finally:
                meshing.NEAR_FEATURES_FIRST = old
            assert np.array_equal(fast[0], full[0])
            assert np.array_equal(fast[1], full[1])
