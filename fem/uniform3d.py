"""Load A in 3D: the whole top face moved down by ``analysis.top_displacement_m`` (u_x, u_y free there); bottom face
u_z = 0 with the rigid-body modes removed minimally (fem.model3d.fixed_bottom); sides traction-free."""
from __future__ import annotations

import time

import numpy as np

from .assembly3d import stiffness3d
from .guards import check_finite
from .model3d import Model3D, build_model3d, fixed_bottom
from .results3d import SurfaceMap, UniformResult3D
from .rigid_stress import with_stone_fields
from .scene import check_load_a
from .stress3d import components3d, recover3d, recovery_operator3d
from .uniform import solve_prescribed


def solve_uniform3d(scene, model: Model3D | None = None, full_field: bool = True,
                    rigid_stones: str | bool = "auto") -> UniformResult3D:
    check_load_a(scene)
    t0 = time.perf_counter()
    model = model or build_model3d(scene, rigid_stones=rigid_stones)
    t1 = time.perf_counter()
    mesh = model.mesh
    top = mesh.top
    base = fixed_bottom(model)
    top_z = model.reduced_index(3 * top + 2)
    fixed = np.concatenate([top_z, base])
    values = np.concatenate([np.full(len(top), -scene.analysis.top_displacement_m), np.zeros(len(base))])
    fac, u_red, u, Ku, residual = solve_prescribed(scene, model, fixed, values)
    t2 = time.perf_counter()
    reaction = -Ku[top_z].sum()
    surf = components3d(recover3d(model, u, top))
    nodal = None
    if full_field:
        nodal = nodal_fields3d(model, u)
    t3 = time.perf_counter()
    check_finite(u, f"load A on scene {scene.name!r}: displacements")
    return UniformResult3D(model=model, u=u, surface=SurfaceMap(mesh.nodes[top, 0], mesh.nodes[top, 1], surf),
                           nodal=nodal, timings_s={"mesh_assemble_s": t1 - t0, "solve_s": t2 - t1,
                                                   "recover_s": t3 - t2},
                           reaction_n=float(reaction), residual=residual)


def nodal_fields3d(model: Model3D, u: np.ndarray) -> dict[str, np.ndarray]:
    """Every node's stress components (Pa) and strains, a rigid stone's nodes included (fem.rigid_stress)."""
    s6, eps = with_stone_fields(model, u, recover3d(model, u), recover3d(model, u, strain=True), stiffness3d,
                                recovery_operator3d, 3)
    nodal = components3d(s6)
    nodal.update({k: eps[:, i] for i, k in enumerate(("exx", "eyy", "ezz", "gyz", "gxz", "gxy"))})
    return nodal
