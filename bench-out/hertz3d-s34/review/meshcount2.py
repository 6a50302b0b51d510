from fem.scene import Analysis, Indenter, Scene, Tissue
from fem.mesh3d import mesh_scene3d
R=0.002
for W,H,f,patch,grade in [(16,8,0.04,2.02,0.7),(16,8,0.04,2.02,0.8),(20,10,0.1,2.02,0.25),(16,8,0.07,2.6,0.45),(16,8,0.1,2.6,0.35)]:
    sc = Scene(name="x", tissue=Tissue(width_m=W*R, length_m=W*R, height_m=H*R, youngs_pa=8000., poisson=0.3),
               stones=(), indenter=Indenter(shape="sphere", radius_m=R),
               analysis=Analysis(order=2, mesh_size_m=2*R, surface_refine=2/f, patch_m=patch*R, grade=grade, top_displacement_m=0.0))
    m=mesh_scene3d(sc); print(W,H,f,patch,grade,"dofs",m.n_dofs, flush=True)
