import sys; sys.path.insert(0, "/tmp/review34")
import numpy as np, time
from hertzref import *
for nu in (0.3, 0.45, 0.49):
    m, z = sphere_axis_max_vm(nu)
    # numeric on axis
    num = sphere_field(np.array([1e-9]*3), np.zeros(3), np.array([0.25, z, 1.0]), nu)
    sr, sz = sphere_axis(np.array([0.25, z, 1.0]), nu)
    print(f"sphere nu={nu}: axis max vM/p0={m:.4f} at z/a={z:.3f}; numeric vs 3.45 at z=0.25,zmax,1:",
          np.round(num[:, [0, 2]].ravel(), 4), np.round(np.c_[sr, sz].ravel(), 4))
    # off-axis search on grid r in [0,1.6], z in [0.05,1.5]
    t = time.time()
    rs = np.linspace(0, 1.6, 33); zs = np.linspace(0.05, 1.5, 30)
    Rg, Zg = np.meshgrid(rs, zs, indexing="ij")
    s = sphere_field(Rg.ravel() + 1e-9, 0 * Rg.ravel(), Zg.ravel(), nu)
    v = vm6(s); j = np.argmax(v)
    print(f"   grid max vM/p0={v[j]:.4f} at r/a={Rg.ravel()[j]:.2f}, z/a={Zg.ravel()[j]:.2f}; max at r>=0.3a: {v[Rg.ravel()>=0.3].max():.4f} ({time.time()-t:.1f}s)")
    # 2D
    mv, xm, zm = cyl_max_vm(nu)
    fl = flamant(0.4, 0.6); mc = mcewen(0.4, 0.6)
    print(f"cylinder nu={nu}: max vM/p0={mv:.4f} at x/a={xm:.3f} z/a={zm:.3f}; Flamant vs McEwen at (0.4,0.6):",
          np.round(fl, 5), np.round(np.array(mc, float), 5))
