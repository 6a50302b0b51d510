"""A stone near a block's side face: fem's contrast at the fitted stone corrects the table's.

The 3D table (planner.surrogate3d) holds a stone's contrast as that of the same stone under the middle of the probed
patch: translation-invariant. Near a side face the true contrast differs (a 10 mm stone 8-13 mm from a side of a
50 mm block: 2.5-3.1 % RMS of the peak over a probe grid, up to 12-19 % at single probes; bench/side3d.py) and a fit
on the table alone comes out several sigma off (docs/localize.md, "A stone near a block's side").

``table_error_n`` is the table's error at one stone, at the probes: fem's contrast of that stone where it is, on the
prior's own mesh (the table's calibration mesh; the prior on the stone's mesh, so the ripple cancels), less the
table's contrast. planner.localize3d adds it, held fixed, to the table's contrast and fits again (a defect
correction: at the fixed point fem's contrast at the fitted stone explains the measurements), again while the stone
moves by more than half its sigma (``SIDE_PASSES`` at most; the passes measured below moved it by 0.2-0.6 of the
previous pass's move). The error taken out is all of the table's at that stone
(the side's effect, its interpolation, its averaging over directions, its mesh calibration).

Measured (session 54, a 50 x 50 x 30 mm block, noise-free records of a 10 mm stone 15 mm from a side, 84 probes):
the table alone 0.38 mm, 1.49 mm and 1.29 mm off in x, depth and diameter (18, 16 and 16 sigma); after 1, 2 and 3
passes the depth 0.50, 0.07 and 0.01 mm off. Not used: the same difference on the table's coarse mesh (the stone
where it is less the stone centred): the coarse mesh's error changes with the stone's place, and the passes wandered
by 0.5 mm in depth without settling. Cost: a stone model and a same-mesh prior on the prior's mesh per pass (about a
minute on a 50 mm block, two on block3d).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from planner.surrogate3d import Grid3D, forces_at, placed_stone_model, same_mesh_prior, table_scene


@dataclass(frozen=True)
class TableError:
    """The table's error at one stone: per probe (N, 0 where fem refuses the waypoint) and what it cost."""
    stone: tuple[float, float, float, float]      # (xs_m, ys_m, depth_m, diameter_m) it was computed at (as meshed)
    error_n: np.ndarray
    solve_s: float


def _same_mesh_contrast(scene, xs: float, ys: float, depth: float, diam: float, x, y, d):
    """(fem's contrast of a rigid stone at (xs, ys) on ``scene``'s mesh, the prior on the stone's mesh, NaN where fem
    refuses a waypoint; (x, y) of the stone as meshed: one the mesher cannot place is moved by a fraction of a
    millimetre, as the table's candidates are). SceneError for a stone no tissue holds (across a side or the
    bottom)."""
    st, model = placed_stone_model(scene, xs, ys, depth, diam)
    f = forces_at(model, x, y, d)
    return f - forces_at(same_mesh_prior(st, model), x, y, d), (st.stones[0].x_m, st.stones[0].y_m)


def table_error_n(prior, sur, stone, x, y, d) -> TableError:
    """The table ``sur``'s error (fem's contrast less the table's) for ``stone`` (xs_m, ys_m, depth_m, diameter_m) in
    the ``prior`` block at probes (x, y) pressed ``d`` deep (levels outside the table's taken at its nearest level;
    0 where fem refuses a waypoint; SceneError for a stone no tissue holds; module doc). ``prior`` has no stones: the
    stone is the fit's, never the truth's. (In this process: planner.forkmap's forked copy of a process that has
    meshed gave no answer within its time-out here.)"""
    if prior.stones:
        raise ValueError("table_error_n() takes the prior scene (no stones)")
    t0 = time.perf_counter()
    x, y = np.asarray(x, float), np.asarray(y, float)
    dc = np.clip(np.asarray(d, float), sur.levels[0], sur.levels[-1])
    xs, ys, depth, diam = (float(v) for v in stone)
    fem_c, (xs, ys) = _same_mesh_contrast(table_scene(prior, Grid3D(), prior.tissue.youngs_pa, own_mesh=True), xs, ys,
                                          depth, diam, x, y, dc)
    err = fem_c - np.asarray(sur.contrast(x, y, dc, xs, ys, depth, diam), float)    # (both at the stone as meshed)
    return TableError((xs, ys, depth, diam), np.where(np.isfinite(err), err, 0.0), time.perf_counter() - t0)
