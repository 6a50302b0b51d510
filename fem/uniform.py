"""Load A of the study: the whole top edge moved down by ``analysis.top_displacement_m`` (u_x free there);
bottom edge u_y = 0, bottom-left corner u_x = 0, sides traction-free."""
from __future__ import annotations

import time
import warnings

import numpy as np

from .guards import check_uniform_result
from .mixed import solve_uniform_mixed
from .model import Model, build_model
from .results import Profile, UniformResult
from .rigid_stress import nodal_fields
from .scene import check_load_a
from .stress import components, nodal_poisson, recovery_operator

# Profile and UniformResult live in fem.results; imported here, they stay importable from fem.uniform too.

RESIDUAL_WARN = 1e-6


def solve_prescribed(scene, model, fixed: np.ndarray, values: np.ndarray):
    """Load A's solve, 2D or 3D: the reduced DOFs ``fixed`` held at ``values``. (factorization, reduced and full
    displacements, K u, relative residual): refused when not finite, a warning when the relative residual exceeds RESIDUAL_WARN."""
    fac = model.partition(fixed)
    pres = np.zeros(len(fac.fixed))
    pres[np.searchsorted(fac.fixed, fixed)] = values
    u_red = fac.solve(pres)
    u = fac.full(u_red)
    if not np.all(np.isfinite(u)):
        raise FloatingPointError(f"load A on scene {scene.name!r}: the solve produced non-finite displacements")
    Ku = model.K @ u_red
    residual = float(np.linalg.norm(Ku[fac.free]) / max(np.linalg.norm(fac.Kfp @ pres), 1e-300))
    if residual > RESIDUAL_WARN:
        warnings.warn(f"load A on scene {scene.name!r}: relative residual {residual:.1e} > {RESIDUAL_WARN:g}: the "
                      f"solution has lost accuracy to round-off (an elastic stone far stiffer than tissue? use "
                      f"rigid_stones='auto')", stacklevel=3)
    return fac, u_red, u, Ku, residual


def solve_uniform(scene, model: Model | None = None, full_field: bool = True,
                  rigid_stones: str | bool = "auto") -> UniformResult:
    check_load_a(scene)
    if scene.analysis.formulation == "mixed":         # locking-free u-p (fem.mixed)
        return check_uniform_result(scene, solve_uniform_mixed(scene, model=model, full_field=full_field,
                                                               rigid_stones=rigid_stones))
    t0 = time.perf_counter()
    model = model or build_model(scene, rigid_stones=rigid_stones)
    t1 = time.perf_counter()
    mesh = model.mesh
    top, bot = mesh.top, mesh.bottom
    corner = bot[0]
    fixed_full = np.concatenate([2 * top + 1, 2 * bot + 1, [2 * corner]])
    values = np.concatenate([np.full(len(top), -scene.analysis.top_displacement_m), np.zeros(len(bot) + 1)])
    fixed = model.reduced_index(fixed_full)
    fac, u_red, u, Ku, residual = solve_prescribed(scene, model, fixed, values)
    t2 = time.perf_counter()
    reaction = -Ku[model.reduced_index(2 * top + 1)].sum()
    plane = model.plane
    R = recovery_operator(model, top)
    surf = components((R @ u).reshape(-1, 3), nodal_poisson(model, top), plane)
    nodal = None
    if full_field:
        allnodes = np.arange(mesh.n_nodes)
        nu = nodal_poisson(model, allnodes)
        s3, eps = nodal_fields(model, u)
        nodal = components(s3, nu, plane)
        nodal.update({"exx": eps[:, 0], "eyy": eps[:, 1], "gxy": eps[:, 2]})
    t3 = time.perf_counter()
    res = UniformResult(model=model, u=u, surface=Profile(mesh.nodes[top, 0], surf), nodal=nodal,
                        timings_s={"mesh_assemble_s": t1 - t0, "solve_s": t2 - t1, "recover_s": t3 - t2},
                        reaction_n_per_m=float(reaction), residual=residual)
    return check_uniform_result(scene, res)
