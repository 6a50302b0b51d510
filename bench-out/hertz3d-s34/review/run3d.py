"""Reviewer's 3D check: SurfaceModel3D.indent max von Mises (stress points) vs own Hertz; also node averages.
usage: run3d.py NU FINE_R GRADE PATCH_R [--mirror]   (prints JSON lines)"""
import sys, json, math, time
sys.path.insert(0, "/tmp/review34")
import numpy as np
from hertzref import sphere_axis_max_vm, sphere_field, vm6
from fem.scene import Analysis, Indenter, Scene, Tissue
from fem.contact3d import surface_model3d
from fem.stress3d import recovery_operator3d, components3d

E, R = 8000.0, 0.002
W, H = 16 * R, 8 * R
nu, f, grade, patch = (float(v) for v in sys.argv[1:5])
mirror = "--mirror" in sys.argv
DEPTHS = (0.02, 0.1) if mirror else (0.02, 0.05, 0.1)
sc = Scene(name=f"rev34_{nu}_{f}", tissue=Tissue(width_m=W, length_m=W, height_m=H, youngs_pa=E, poisson=nu),
           stones=(), indenter=Indenter(shape="sphere", radius_m=R),
           analysis=Analysis(order=2, mesh_size_m=3 * R, surface_refine=3 / f, patch_m=patch * R, grade=grade,
                             top_displacement_m=0.0))
t0 = time.time()
sm = surface_model3d(sc, cache=False)
tb = time.time() - t0
mesh, model = sm.mesh, sm.model
c = W / 2
pos = [(c, c)]
if mirror:
    dx, dy = 0.27 * R, 0.11 * R
    pos = [(c, c), (c - dx, c + dy), (W - (c - dx), c + dy), (c - dx, W - (c + dy))]   # x -> W-x and y -> W-y
wps = [(x, y, dr * R) for (x, y) in pos for dr in DEPTHS]
res = sm.indent_many(wps, stresses=True)
Es = E / (1 - nu ** 2)
hvm, hz = sphere_axis_max_vm(nu)
# nodes for the node-averaged maximum (same box as the tool's search: |dx|,|dy| <= 2R, depth <= 2R, tissue nodes)
for (x, y, d), r in zip(wps, res):
    F = r.force_n
    a = (3 * F * R / (4 * Es)) ** (1 / 3); p0 = 3 * F / (2 * math.pi * a * a)
    Fh = 4 / 3 * Es * math.sqrt(R) * d ** 1.5
    xm, ym, zm = r.max_von_mises_at_m
    u = sm.full_field(x, y, d)
    N = mesh.nodes
    near = np.flatnonzero((np.abs(N[:, 0] - x) <= 2 * R) & (np.abs(N[:, 1] - y) <= 2 * R) & (N[:, 2] >= H - 2 * R))
    Rn = recovery_operator3d(model, near)
    vmn = components3d((Rn @ u).reshape(-1, 6))["von_mises_pa"]
    jn = int(np.argmax(vmn))
    # exact Hertz stress at the FE maximum's point (centred on the tip, a and p0 of the FE force)
    Xs = sm._band_op()[0]
    lat = np.hypot(Xs[:, 0] - x, Xs[:, 1] - y); dep = H - Xs[:, 2]
    sel = np.flatnonzero((lat <= 0.6 * a) & (dep >= 0.25 * a) & (dep <= 0.9 * a))
    samp = float(vm6(sphere_field(Xs[sel, 0] - x, Xs[sel, 1] - y, dep[sel], nu, a=a, p0=p0)).max())
    ex = vm6(sphere_field(np.array([xm - x]), np.array([ym - y]), np.array([zm]), nu, a=a, p0=p0))[0]
    out = dict(nu=nu, fine_over_r=f, grade=grade, patch_over_r=patch, dofs=mesh.n_dofs, build_s=round(tb, 1),
               x_off_over_r=round((x - c) / R, 3), y_off_over_r=round((y - c) / R, 3), d_over_r=d / R,
               a_over_r=a / R, elems_per_a=a / (f * R), force_n=F, force_vs_hertz=F / Fh - 1,
               max_vm_pa=r.max_von_mises_pa, vm_vs_hertz=r.max_von_mises_pa / (hvm * p0) - 1,
               vm_depth_over_a=zm / a, vm_lateral_over_a=math.hypot(xm - x, ym - y) / a,
               hertz_depth_over_a=hz, fe_over_exact_at_point=r.max_von_mises_pa / ex - 1, sampled_exact_max_vs_hertz=samp / (hvm * p0) - 1,
               node_vm_vs_hertz=float(vmn[jn]) / (hvm * p0) - 1,
               node_vm_depth_over_a=float(H - N[near[jn], 2]) / a,
               node_vm_lateral_over_a=float(math.hypot(N[near[jn], 0] - x, N[near[jn], 1] - y)) / a)
    print(json.dumps({k: (round(v, 4) if isinstance(v, float) else v) for k, v in out.items()}), flush=True)
