"""Checks on results before they leave fem (issue 13): no inverted element, no non-finite number.

A linear small-strain solution is a displacement field; added to the mesh it may fold elements over (a surface
pushed through a rigid stone, a thin tissue indented most of its thickness). Such an answer has no meaning, so the
deformed element Jacobians are checked (vectorised over the elements, at the quadrature points and the nodes) and
any det J <= 0 is refused. Every number that leaves fem (results, their ``to_dict``) is checked finite.
"""
from __future__ import annotations

import warnings

import numpy as np

from .elements import nodes_ref, quadrature, shape_grad
from .mesh import Mesh
from .scene import STRAIN_MAX, STRAIN_WARN, SceneError


class InvertedElementsError(SceneError):
    """A solution that folds elements over (det J <= 0 in the deformed mesh): outside the linear model."""


class NonFiniteResultError(SceneError):
    """A result with a NaN or an infinity in it."""


def deformation(mesh: Mesh, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(det J of each deformed element, smallest over its quadrature points and nodes; its largest principal strain
    magnitude) for the full displacement vector u (2N,), or u (2N, k) for k load cases: arrays (k, M)."""
    U = np.asarray(u, float).reshape(mesh.n_nodes, 2, -1)
    pts = np.vstack([quadrature(2 * (mesh.order - 1))[0], nodes_ref(mesh.order)])
    G = shape_grad(mesh.order, pts)                                    # (q, a, 2)
    J0 = np.tensordot(mesh.nodes[mesh.tris], G, axes=([1], [1])).transpose(0, 2, 1, 3)      # (M, q, 2, 2)
    Ju = np.tensordot(U[mesh.tris], G, axes=([1], [1])).transpose(2, 0, 3, 1, 4)         # (k, M, q, 2, 2)
    J = J0[None] + Ju
    det = (J[..., 0, 0] * J[..., 1, 1] - J[..., 0, 1] * J[..., 1, 0]).min(axis=2)
    d0 = J0[..., 0, 0] * J0[..., 1, 1] - J0[..., 0, 1] * J0[..., 1, 0]
    inv = np.stack([np.stack([J0[..., 1, 1], -J0[..., 0, 1]], -1),
                    np.stack([-J0[..., 1, 0], J0[..., 0, 0]], -1)], -2) / d0[..., None, None]
    H = Ju @ inv[None]                                                  # displacement gradient
    exx, eyy, exy = H[..., 0, 0], H[..., 1, 1], 0.5 * (H[..., 0, 1] + H[..., 1, 0])
    strain = (np.abs(0.5 * (exx + eyy)) + np.sqrt((0.5 * (exx - eyy)) ** 2 + exy ** 2)).max(axis=2)
    return det, strain


def check_not_inverted(mesh: Mesh, u: np.ndarray, what: str, hint: str) -> np.ndarray:
    """InvertedElementsError naming ``what`` and ``hint`` if any element of the deformed mesh folds over; else the
    largest principal strain per load case (k,)."""
    det, strain = deformation(mesh, u)
    bad = ~(det > 0)
    if bad.any():
        k = int(np.argmax(bad.sum(axis=1)))
        raise InvertedElementsError(f"{what}: {int(bad[k].sum())} of {bad.shape[1]} elements turn inside out "
                                    f"(det J <= 0) under this load, largest strain {strain[k].max():.0%}: the "
                                    f"linear small-strain model does not hold; {hint}")
    return strain.max(axis=1)


def _first_nonfinite(obj, path: str):
    if isinstance(obj, dict):
        for k, v in obj.items():
            hit = _first_nonfinite(v, f"{path}.{k}")
            if hit:
                return hit
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            hit = _first_nonfinite(v, f"{path}[{i}]")
            if hit:
                return hit
    elif isinstance(obj, np.ndarray):
        if obj.dtype.kind in "fc" and not np.all(np.isfinite(obj)):
            i = np.flatnonzero(~np.isfinite(obj.ravel()))[0]
            return f"{path}[{int(i)}]", obj.ravel()[i]
    elif isinstance(obj, (float, np.floating)) and not np.isfinite(obj):
        return path, obj
    return None


def check_finite(obj, what: str):
    """``obj`` (a number, an array, or dicts / lists of them) unchanged; NonFiniteResultError naming the first
    non-finite entry otherwise."""
    hit = _first_nonfinite(obj, "")
    if hit:
        path, value = hit
        raise NonFiniteResultError(f"{what}: {path.lstrip('.') or 'the value'} = {value} is not finite (the scene's "
                                   f"numbers are beyond what the model computes in double precision)")
    return obj


def check_uniform_result(scene, res):
    """Load A's result (fem.results.UniformResult) unchanged after its checks: finite displacements, reaction and
    surface stresses, no inverted element; a warning when the applied strain top_displacement_m / height_m exceeds
    the linear model's stated STRAIN_WARN (validate refuses above STRAIN_MAX)."""
    what = f"load A on scene {scene.name!r}"
    check_finite({"u": res.u, "reaction_n_per_m": res.reaction_n_per_m, "surface": res.surface.fields,
                  "nodal": res.nodal or {}}, what)
    check_not_inverted(res.model.mesh, res.u, what, "lower analysis.top_displacement_m")
    strain = scene.analysis.top_displacement_m / scene.tissue.height_m
    if strain > STRAIN_WARN * (1 + 1e-9):
        warnings.warn(f"{what}: top_displacement_m / height_m = {strain:.0%} exceeds the {STRAIN_WARN:.0%} the "
                      f"linear small-strain model is stated for (refused above {STRAIN_MAX:.0%}): stresses are "
                      f"a linear extrapolation", stacklevel=3)
    return res
