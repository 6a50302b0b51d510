"""Reviewer's 2D check: SurfaceModel.indent max von Mises (node averages) under a rigid cylinder vs Hertz line
contact (McEwen, plane strain), plus the reviewer's own max over the P2 triangles' degree-2 points.
usage: run2d.py NU D_OVER_R FOCUS_SIZE_OVER_A_GUESS..."""
import sys, json, math
sys.path.insert(0, "/tmp/review34")
import numpy as np
from hertzref import mcewen, vm_plane_strain, cyl_max_vm
from fem.scene import Analysis, Indenter, Scene, Tissue
from fem.contact import SurfaceModel
from fem.mesh import mesh_section
from fem.model import build_model
from fem.assembly import gradients, strain_matrices, element_dofs
from fem.elements import quadrature, shape

E, R = 8000.0, 0.01
W, H = 20 * R, 10 * R
nu, dr = float(sys.argv[1]), float(sys.argv[2])
fracs = [float(v) for v in sys.argv[3:]]
Es = E / (1 - nu ** 2)
hvm, hx, hz = cyl_max_vm(nu)
a_guess = None
for fr in fracs:
    sc = Scene(name="h2", tissue=Tissue(width_m=W, height_m=H, youngs_pa=E, poisson=nu),
               indenter=Indenter(radius_m=R), analysis=Analysis(mesh_size_m=0.01, surface_refine=1.0, top_displacement_m=0.0))
    ag = a_guess if a_guess else 0.1 * R
    fsize = fr * ag
    mesh = mesh_section(W, H, [], 0.01, 1.0, 2, focus=(W / 2, fsize, 4 * ag))
    model = build_model(sc, mesh=mesh)
    m = SurfaceModel(sc, model=model)
    x0 = W / 2
    r = m.indent(x0, dr * R)
    P = r.force_n_per_m
    a = math.sqrt(4 * P * R / (math.pi * Es)); p0 = 2 * P / (math.pi * a)
    if a_guess is None:
        a_guess = a
    xm, zm = r.max_von_mises_at_m
    ex = vm_plane_strain(*[float(v) for v in mcewen(xm - x0, max(zm, 1e-12 * a), a, p0)], nu)
    # own: degree-2 points of tissue elements within 2R below the surface and |x - x0| <= 2R
    u = m.full_field(x0, dr * R) if hasattr(m, "full_field") else None
    if u is None:
        F = np.zeros((len(m.top), 1)); idx, f, _ = m.contact_forces(x0, dr * R); F[idx, 0] = f
        u = m.displacements(F)[:, 0]
    pts = quadrature(2)[0]
    c = mesh.nodes[mesh.tris[:, :3]].mean(axis=1)
    els = np.flatnonzero((mesh.region == 0) & (c[:, 1] >= H - 2 * R) & (np.abs(c[:, 0] - x0) <= 2 * R))
    sub = type(mesh)(nodes=mesh.nodes, tris=mesh.tris[els], region=mesh.region[els], order=mesh.order,
                     width_m=mesh.width_m, height_m=mesh.height_m, top=mesh.top, bottom=mesh.bottom)
    G, _ = gradients(sub, pts)
    B = np.einsum("mkl,mqln->mqkn", model.D[els], strain_matrices(G))
    s = np.einsum("mqkn,mn->mqk", B, u[element_dofs(mesh)[els]])
    vmq = vm_plane_strain(s[..., 0], s[..., 1], s[..., 2], nu)
    X = np.einsum("qa,mai->mqi", shape(2, pts), mesh.nodes[mesh.tris[els]])
    j = np.unravel_index(np.argmax(vmq), vmq.shape)
    qx, qz = X[j][0] - x0, H - X[j][1]
    # sampled exact max over these points (what an exact field would give at the same points)
    near = (np.abs(X[..., 0] - x0) < 0.5 * a) & (H - X[..., 1] > 0.4 * a) & (H - X[..., 1] < 1.2 * a)
    ex_s = vm_plane_strain(*mcewen(X[..., 0][near] - x0, H - X[..., 1][near], a, p0), nu).max()
    out = dict(nu=nu, d_over_r=dr, a_over_r=a / R, elem_over_a=fsize / a, n_nodes=mesh.nodes.shape[0],
               node_vm_vs_hertz=r.max_von_mises_pa / (hvm * p0) - 1, node_depth_over_a=zm / a,
               node_lateral_over_a=(xm - x0) / a, node_fe_over_exact_at_point=r.max_von_mises_pa / ex - 1,
               pressure_max_vs_p0=float(np.max(r.pressure_pa)) / p0 - 1,
               gauss_vm_vs_hertz=float(vmq[j]) / (hvm * p0) - 1, gauss_depth_over_a=qz / a, gauss_lateral_over_a=qx / a,
               sampled_exact_vs_hertz=float(ex_s) / (hvm * p0) - 1, hertz_depth_over_a=hz)
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in out.items()}), flush=True)
