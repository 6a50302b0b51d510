"""The disk cache's entry points under their historical names (``fem.cache.mesh_for`` etc.).

The cache itself is generic and lives in fem.diskcache (key -> arrays, imports nothing from fem); the modules that
know how to build something use it: fem.scene_mesh (a scene's mesh) and fem.contact (a scene's SurfaceModel). This
module only re-exports their names for existing callers; nothing inside fem imports it.
"""
from __future__ import annotations

from .contact import load_or_build_surface, surface_key
from .diskcache import cache_dir, enabled, stats
from .scene_mesh import checked_mesh, code_version, mesh_for, mesh_key

__all__ = ["cache_dir", "checked_mesh", "code_version", "enabled", "load_or_build_surface", "mesh_for", "mesh_key",
           "stats", "surface_key"]
