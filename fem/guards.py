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


def check_points(mesh: Mesh, elements: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(shape gradients G (q, a, 2) at the check points: the quadrature points and the nodes; reference Jacobians
    J0 (M, q, 2, 2) of the ``elements`` (all when None) there)."""
    pts = np.vstack([quadrature(2 * (mesh.order - 1))[0], nodes_ref(mesh.order)])
    G = shape_grad(mesh.order, pts)                                    # (q, a, 2)
    tris = mesh.tris if elements is None else mesh.tris[elements]
    J0 = np.tensordot(mesh.nodes[tris], G, axes=([1], [1])).transpose(0, 2, 1, 3)          # (M, q, 2, 2)
    return G, J0


def displacement_gradients(U_el: np.ndarray, G: np.ndarray, J0: np.ndarray) -> np.ndarray:
    """Displacement gradients H (k, M, q, 2, 2) at the check points from the elements' nodal displacements U_el
    (M, a, 2, k): the deformed Jacobian is J0 (I + H)."""
    Ju = np.tensordot(U_el, G, axes=([1], [1])).transpose(2, 0, 3, 1, 4)                  # (k, M, q, 2, 2)
    d0 = J0[..., 0, 0] * J0[..., 1, 1] - J0[..., 0, 1] * J0[..., 1, 0]
    inv = np.stack([np.stack([J0[..., 1, 1], -J0[..., 0, 1]], -1),
                    np.stack([-J0[..., 1, 0], J0[..., 0, 0]], -1)], -2) / d0[..., None, None]
    return Ju @ inv[None]


def deformation(mesh: Mesh, u: np.ndarray, elements: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(det J of each deformed element, smallest over its quadrature points and nodes; its largest principal strain
    magnitude) for the full displacement vector u (2N,), or u (2N, k) for k load cases: arrays (k, M) over the
    ``elements`` (all when None)."""
    U = np.asarray(u, float).reshape(mesh.n_nodes, 2, -1)
    G, J0 = check_points(mesh, elements)
    H = displacement_gradients(U[mesh.tris if elements is None else mesh.tris[elements]], G, J0)
    return det_and_strain(H, J0)


def det_and_strain(H: np.ndarray, J0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(smallest det J0 (I + H) over the check points, largest principal strain magnitude): arrays (k, M) from
    displacement gradients H (k, M, q, 2, 2) and reference Jacobians J0 (M, q, 2, 2)."""
    d0 = J0[..., 0, 0] * J0[..., 1, 1] - J0[..., 0, 1] * J0[..., 1, 0]
    A = H + np.eye(2)
    det = (d0[None] * (A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0])).min(axis=2)
    exx, eyy, exy = H[..., 0, 0], H[..., 1, 1], 0.5 * (H[..., 0, 1] + H[..., 1, 0])
    strain = (np.abs(0.5 * (exx + eyy)) + np.sqrt((0.5 * (exx - eyy)) ** 2 + exy ** 2)).max(axis=2)
    return det, strain


def inverted_error(what: str, hint: str, n_bad: int, n_elements: int, strain_max: float) -> InvertedElementsError:
    return InvertedElementsError(f"{what}: {n_bad} of {n_elements} elements turn inside out (det J <= 0) under "
                                 f"this load, largest strain {strain_max:.0%}: the linear small-strain model does "
                                 f"not hold; {hint}")


def check_not_inverted(mesh: Mesh, u: np.ndarray, what: str, hint: str) -> np.ndarray:
    """InvertedElementsError naming ``what`` and ``hint`` if any element of the deformed mesh folds over; else the
    largest principal strain per load case (k,)."""
    det, strain = deformation(mesh, u)
    bad = ~(det > 0)
    if bad.any():
        k = int(np.argmax(bad.sum(axis=1)))
        raise inverted_error(what, hint, int(bad[k].sum()), bad.shape[1], float(strain[k].max()))
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
