import sys
from fem.scene import Analysis, Indenter, Scene, Tissue
from fem.mesh3d import estimate_nodes3d
R=0.002
for W,H in [(20*R,10*R),(16*R,8*R)]:
  for f in [0.1,0.07,0.05]:
    for patch in [2.02*R, 2.6*R]:
      for grade in [0.25,0.35]:
        sc = Scene(name="x", tissue=Tissue(width_m=W, length_m=W, height_m=H, youngs_pa=8000., poisson=0.3),
                   stones=(), indenter=Indenter(shape="sphere", radius_m=R),
                   analysis=Analysis(order=2, mesh_size_m=3*R, surface_refine=3/f, patch_m=patch, grade=grade, top_displacement_m=0.0))
        e=estimate_nodes3d(sc); print(W/R,H/R,f,patch/R,grade,{k:round(v) for k,v in e.items()})
