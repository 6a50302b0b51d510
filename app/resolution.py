"""A 2D contact the top's mesh does not resolve: one warning line (the 3D one: app.commands.sim3d.warn_unresolved).

Measured (session 47), the healthy paper section (E 2500 Pa, nu 0.4, a 5 mm cylinder) at depths 0.1-0.5 mm against
the same section with a top 8 times finer (`palpate simulate healthy --load indent --x-m 0.035 --depth-m D
--surface-refine 4 / 8 / 32`): at 0.8-2.5 of the top's elements across the contact half-width the force is within
1.4 % and the peak pressure 1.6-8.8 % high; from 4 elements both within 0.2 %. An independent review's section (E
20 kPa, nu 0.3, a 4 mm cylinder, 4 mm elements at depth) below one element: force -9 to +11 %, peak pressure down to
-53 %, maximum von Mises -49 to +13 %. Session 60's review (the paper-like section, 0.5 mm top elements, 1 um deep,
one node carrying the contact) against a 15.6 um top: force +28 %, peak pressure and maximum von Mises -80 %; and a
tip 1 um deep between two nodes touched none (force 0, said since).
"""
from __future__ import annotations

import math
import sys

RESOLVED_ELEMENTS = 3.0      # the contact half-width over the top's element size below which the line is printed
NU_PRESSURE_WARN = 0.49      # tissue Poisson ratio from which the nodal contact pressure's oscillation is said


def top_element_m(scene) -> float:
    """The element size along the top surface, m (fem.mesh: mesh_size_m / surface_refine)."""
    return scene.analysis.mesh_size_m / scene.analysis.surface_refine


def warn_unresolved2d(scene, command: str, half_widths_m, stresses: bool = True, depths_m=None) -> None:
    """One line on stderr when the smallest contact half-width of ``half_widths_m`` (those in contact) spans fewer
    than RESOLVED_ELEMENTS of the top's elements; or, given ``depths_m``, when a tip pressed in touched no top node at
    all (its footprint fell between two nodes: a force of 0 that is the mesh's, not the tissue's)."""
    a = [w for w in half_widths_m if w > 0]
    h = top_element_m(scene)
    if depths_m is not None:
        missed = [d for w, d in zip(half_widths_m, depths_m) if w <= 0 and d > 0]
        if missed:
            d = min(missed)
            R = scene.indenter.radius_m
            b = math.sqrt(max(2 * R * d - d * d, 0.0)) if scene.indenter.shape == "cylinder" else R
            print(f"palpate {command}: {scene.name}: warning: the tip pressed {d:.3g} m in touched no node of the top "
                  f"(its footprint, {2 * b * 1e3:.3g} mm wide, fell between nodes {h / scene.analysis.order * 1e3:.3g}"
                  f" mm apart): the force 0 is the mesh's, not the tissue's; raise analysis.surface_refine (now "
                  f"{scene.analysis.surface_refine:g}) or indent deeper", file=sys.stderr)
    if not a:
        return
    k = min(a) / h
    if k >= RESOLVED_ELEMENTS:
        return
    what = "the peak pressure and the maximum von Mises are" if stresses else "the contact's pressure is"
    print(f"palpate {command}: {scene.name}: warning: the contact half-width spans {k:.2g} of the top's elements "
          f"({h * 1e3:.3g} mm) at its smallest, under {RESOLVED_ELEMENTS:g}: {what} not resolved there and the "
          f"force may be off (measured: at 0.8-2.5 elements force within 1.4 %, pressure up to +9 %; below one "
          f"element reviews found force -9 to +28 % and pressure and stress peaks up to 80 % off, the most where "
          f"one node carries the whole contact); raise analysis.surface_refine (now "
          f"{scene.analysis.surface_refine:g}) or indent deeper", file=sys.stderr)


def warn_pressure_near_incompressible2d(scene, command: str, half_widths_m) -> None:
    """One line on stderr when the tissue's Poisson ratio is NU_PRESSURE_WARN or more and a contact was found: the
    P2 displacement form's nodal contact pressure then oscillates between corner and mid-side nodes, and its peak
    is high until the contact spans many elements, while the force and the maximum von Mises converge. Measured
    (session 59, an independent review's section: 160 x 80 mm, E 20 kPa, a rigid 4 mm cylinder 0.3 mm deep,
    plane strain; `palpate simulate SCENE --load indent --surface-refine 32 / 64`), against Hertz's p0 for the
    force fem found: at nu 0.49 +10 % with 5.2 elements across the half-width, +2.6 % with 10.4; at 0.499 +54 % and
    +18 %; between those meshes the force moved 0.03 % and the maximum von Mises 0.3 % (0.49) and 0.9 % (0.499);
    at nu 0.3-0.45 the same meshes gave +0.2 to +1.6 %."""
    nu = scene.tissue.poisson
    a = [w for w in half_widths_m if w > 0]
    if nu < NU_PRESSURE_WARN or not a:
        return
    k = min(a) / top_element_m(scene)
    print(f"palpate {command}: {scene.name}: warning: tissue poisson = {nu:g} (near incompressible): the nodal "
          f"contact pressure oscillates between neighbouring nodes and its peak is high (measured: +10 % at nu 0.49 "
          f"and +54 % at 0.499 with 5 elements across the half-width, +2.6 % and +18 % with 10; here {k:.2g}); the "
          f"force and the maximum von Mises converge (within 1 % there); raise analysis.surface_refine (now "
          f"{scene.analysis.surface_refine:g}) for the pressure", file=sys.stderr)
