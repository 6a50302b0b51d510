"""palpate's finite-element package: scenes, meshes, load A (uniform compression) and load B (tip contact).

The names in ``__all__`` are the public API, each imported from its module on first use (core.lazy). Importing fem
stays light: scipy is imported only when a model is assembled, factorized or its stress operators built (a scene
whose surface operators come from the disk cache predicts with numpy alone), gmsh and meshio only when a mesh is
built or a file written, and matplotlib only by ``fem.plots`` (import it explicitly).

Modules (each imports only modules listed before it; tests/test_fem_imports.py checks there is no cycle):
  scene       Scene, Tissue, Stone, Indenter, Analysis, SceneError, load, from_dict (TOML scenes, built-ins)
  elements    P1/P2 shape functions and quadrature
  lcp         the contact LCP solver (solve_lcp)
  diskcache   generic key -> arrays disk cache (imports nothing from fem)
  memo        float keys -> float rows, remembered between runs on the disk cache (Memo)
  mesh        Mesh (to_arrays/from_arrays) and gmsh meshing: mesh_section, mesh_scene, mesh_tip
  scene_mesh  a scene's checked mesh from the disk cache or gmsh: mesh_for
  assembly    vectorized stiffness assembly
  model       Model, build_model (rigid stones), accuracy warnings
  stress      nodal stress recovery: recovery_operator, nodal_poisson, components
  results     Profile, UniformResult (load A results)
  mixed       load A, locking-free Taylor-Hood u-p
  uniform     load A: solve_uniform (dispatches to mixed)
  tip         TipCompliance (an elastic tip), rigid_tip_bound, treated_as_rigid, contact_scene (what a key names)
  influence   influence operators of the top nodes: stresses and the no-inversion check at the cost of forces
  contact     load B: SurfaceModel, surface_model (memory + disk cache), indent_full, tip_profile, check_waypoint
  recall      a scene's contact forces as computed before (fem.memo): force_n, force_curve_n, known
  export      VTU export (meshio): write_vtu, write_result_vtu
  plots       figures (matplotlib), not imported here
  cache       historical names of the disk-cache entry points (mesh_for, mesh_key, surface_key, stats, ...)

3D (issue 15; a tissue with length_m), imported explicitly (not re-exported here):
  elements3d  P1/P2 tetrahedra, quadrature (degree 5 for curved P2 elements)
  mesh3d      Mesh3D and gmsh meshing of a block with spherical stones (mesh_block, mesh_scene3d)
  scene_mesh3d  a 3D scene's checked mesh from the disk cache or gmsh: mesh_for3d
  assembly3d  vectorized 3D stiffness assembly
  model3d     Model3D (rigid stones with 6 DOFs), fixed_bottom (u_z = 0, rigid modes removed minimally)
  stress3d    3D nodal stress recovery
  results3d   SurfaceMap (top-face stress map, its peak), UniformResult3D
  uniform3d   load A in 3D: solve_uniform3d
  condense    Schur condensation onto contact DOFs and a sparse Cholesky (CHOLMOD via cvxopt; SuperLU fallback)
  contact3d   load B in 3D: SurfaceModel3D, surface_model3d (memory + disk cache), check_waypoint3d
  recall3d    a 3D scene's contact forces as computed before (fem.memo): force_n, known
  export3d    VTU export of tetrahedral meshes
  plots3d     3D figures (matplotlib), not imported here

The finite-strain simulated truth (issue 14; 2D), imported explicitly (not re-exported here):
  neohooke    the compressible neo-Hookean law (stress, consistent tangent) in plane strain
  finite_strain  total-Lagrangian internal force and tangent stiffness on a Model
  hyperindent the rigid tip in exact frictionless contact with a neo-Hookean tissue: Newton + LCP, sweeps in depth
  hypertruth  the finite-strain simulated truth's force (per x, disk-cached), for robot.simarm only
"""
from core.lazy import lazy_exports

_EXPORTS = {
    "IndentResult": "contact", "SurfaceModel": "contact", "check_waypoint": "contact", "indent_full": "contact",
    "surface_model": "contact", "tip_profile": "contact", "write_result_vtu": "export", "write_vtu": "export",
    "solve_lcp": "lcp", "Mesh": "mesh", "mesh_scene": "mesh", "mesh_section": "mesh", "Model": "model",
    "build_model": "model", "Profile": "results", "UniformResult": "results", "Analysis": "scene",
    "Indenter": "scene", "Scene": "scene", "SceneError": "scene", "Stone": "scene", "Tissue": "scene",
    "from_dict": "scene", "load": "scene", "mesh_for": "scene_mesh", "components": "stress",
    "nodal_poisson": "stress", "recovery_operator": "stress", "solve_uniform": "uniform",
}
__all__ = sorted(_EXPORTS)   # see the module docstring for where each name lives
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
