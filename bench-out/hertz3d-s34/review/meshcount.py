import sys, time
from fem.scene import Analysis, Indenter, Scene, Tissue
from fem.mesh3d import estimate_nodes3d, mesh_scene3d
R=0.002
W,H=16*R,8*R
for f,patch,grade in [(0.1,2.02,0.25),(0.07,2.02,0.25),(0.07,2.02,0.3),(0.07,2.6,0.4),(0.1,2.6,0.3),(0.05,2.02,0.5)]:
    sc = Scene(name="x", tissue=Tissue(width_m=W, length_m=W, height_m=H, youngs_pa=8000., poisson=0.3),
               stones=(), indenter=Indenter(shape="sphere", radius_m=R),
               analysis=Analysis(order=2, mesh_size_m=3*R, surface_refine=3/f, patch_m=patch*R, grade=grade, top_displacement_m=0.0))
    t=time.time(); m=mesh_scene3d(sc); print(f,patch,grade,"nodes",m.n_nodes,"dofs",m.n_dofs,"est",round(estimate_nodes3d(sc)["dofs"]), "%.1fs"%(time.time()-t), flush=True)
