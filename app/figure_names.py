"""The figures each command draws into its ``--plots`` directory, by file name: one place, so that a command can
refuse an output path that is one of them (``app.options.refuse_figures``) without loading the code that draws them
(the 3D path loads scipy.linalg and CHOLMOD)."""
from __future__ import annotations

FIG_INDENT_2D = "fig10_indent.png"                               # simulate --load indent, 2D
FIG_PREDICT_2D = "fig11_predict.png"                             # predict, 2D
FIG_UNIFORM_3D = ("fig3d_surface.png", "fig3d_section.png")      # simulate --load uniform, 3D
FIG_INDENT_3D = ("fig3d_indent_surface.png", "fig3d_indent_section.png")   # simulate --load indent, 3D
FIG_PREDICT_3D = "fig3d_predict.png"                             # predict, 3D
PLAN_FIGURES = ("plan_raster.png", "plan_area.png", "plan_joints.png")     # plan (2D: raster, 3D: area; joints)
