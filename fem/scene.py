"""Scenes: the tissue section (or block), the stones in it, the probe tip and analysis options.

All quantities are SI (m, Pa). The 2D section lies in the x-y plane: x from the left edge (0 .. width_m),
y up from the bottom edge (0 .. height_m). A stone's ``depth_m`` is the depth of its centre below the top surface.

3D (issue 15): a tissue with ``length_m`` is a block x in [0, width_m], y in [0, length_m], z up from the bottom
face (0 .. height_m); its stones are spheres placed by ``x_m``, ``y_m`` and ``depth_m``; its tip is a ``sphere`` (or
a circular ``flat`` punch) of radius ``radius_m``. ``analysis.patch_m`` is the side of the centred square of the top
face that is probed (graded finer and condensed for contact; None: the whole face). A 2D scene has none of these
fields (its dict, TOML and cache keys are unchanged).

A scene plays two roles in a simulated run (see docs/architecture.md, "Truth and belief"): the simulator holds the full scene
(the truth), the planner and the localizer hold ``scene.prior()`` — the same tissue with its stones removed.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from core.textfile import NESTED_TOO_DEEP, read_user_text


class SceneError(ValueError):
    """A scene description that cannot be used; the message names the offending field."""


@dataclass(frozen=True)
class Tissue:
    width_m: float = 0.070
    height_m: float = 0.050
    youngs_pa: float = 2500.0
    poisson: float = 0.4
    length_m: float | None = None    # 3D: the block's extent along y (None: a 2D plane section)


@dataclass(frozen=True)
class Stone:
    x_m: float
    depth_m: float
    diameter_m: float
    youngs_pa: float = 5.0e9
    poisson: float = 0.3
    y_m: float | None = None         # 3D: the sphere's centre along y (None in a 2D scene)

    @property
    def radius_m(self) -> float:
        return 0.5 * self.diameter_m


@dataclass(frozen=True)
class Indenter:
    shape: str = "cylinder"          # 2D: "cylinder" or "flat" (half-width radius_m); 3D: "sphere" or "flat" (disk)
    radius_m: float = 0.005
    youngs_pa: float | None = None   # None: rigid tip
    poisson: float = 0.3
    thickness_m: float = 0.020       # out-of-plane length: force_n = force_n_per_m * thickness_m


@dataclass(frozen=True)
class Analysis:
    plane: str = "strain"            # "strain" or "stress"
    order: int = 2                   # 1: P1 triangles, 2: P2 triangles
    mesh_size_m: float = 0.002       # element size at depth; the top surface and stones are graded finer
    surface_refine: float = 4.0      # size at the top surface = mesh_size_m / surface_refine
    top_displacement_m: float = 0.005  # load A: the whole top edge moved down by this much
    formulation: str = "displacement"  # "displacement" (P1/P2) or "mixed" (Taylor-Hood P2/P1 u-p, locking-free)
    patch_m: float | None = None     # 3D: side of the centred probed square of the top face (None: the whole face)
    grade: float | None = None       # 3D: element size growth per unit distance from the patch and stones (None: 0.5)


@dataclass(frozen=True)
class Scene:
    name: str = "paper"
    tissue: Tissue = field(default_factory=Tissue)
    stones: tuple[Stone, ...] = ()
    indenter: Indenter = field(default_factory=Indenter)
    analysis: Analysis = field(default_factory=Analysis)

    def __post_init__(self):
        object.__setattr__(self, "stones", tuple(self.stones))
        validate(self)

    @property
    def is_3d(self) -> bool:
        """A block (tissue.length_m given), not a plane section."""
        return self.tissue.length_m is not None

    def prior(self) -> Scene:
        """What a surgeon knows before probing: the tissue, no stones."""
        return dataclasses.replace(self, name=f"{self.name}-prior", stones=())

    def with_analysis(self, **changes) -> Scene:
        return dataclasses.replace(self, analysis=dataclasses.replace(self.analysis, **changes))

    def with_stones(self, stones) -> Scene:
        return dataclasses.replace(self, stones=tuple(stones))

    def to_dict(self) -> dict:
        def given(obj) -> dict:     # None = not given (a 2D scene's dict has no 3D key)
            return {k: v for k, v in dataclasses.asdict(obj).items() if v is not None}
        d = {"name": self.name, "tissue": given(self.tissue), "stone": [given(s) for s in self.stones],
             "indenter": given(self.indenter), "analysis": given(self.analysis)}
        return d

    def key(self) -> str:
        """A content hash: equal scenes (whatever their name) give equal keys."""
        d = self.to_dict()
        d.pop("name")
        if d["analysis"].get("formulation") == "displacement":   # keys from before the field existed stay valid
            del d["analysis"]["formulation"]
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


# ---------------------------------------------------------------------------------------------------------------
# Bounds (issue 13): what the linear small-strain model and double precision represent. Each is wider than every
# built-in scene, test and bench scene; a value outside is refused with a message naming the field, its value and
# the allowed range (never clamped, never a silent default).

# Young's moduli. Physical materials span about 1e2 Pa (soft gels) to 1.2e12 Pa (diamond); the bounds leave six
# decades either side (tests round-trip 1e-5 and 1.5e16) while keeping stiffness entries, compliances (1/E) and
# stresses (E * strain) far inside double precision: 1e-300 Pa gave zero stresses everywhere, 1e300 Pa inf.
MODULUS_MIN_PA = 1.0e-6
MODULUS_MAX_PA = 1.0e18
# Lengths (tissue width and height, stone diameter, tip radius and thickness): 10 um .. 10 m. Below, the geometry
# is under gmsh's default tolerances (1e-8 relative); above, no tissue section (and no robot's reach); 1e300 m made
# OpenCASCADE fail and an infinite gap.
LENGTH_MIN_M = 1.0e-5
LENGTH_MAX_M = 10.0
# The finest element (mesh_size_m / surface_refine) must be at least 1 um: below, gmsh works at its tolerance and the
# mesh of even a 1 mm section has millions of DOFs (the DOF cap in fem.scene_mesh refuses big meshes separately).
ELEMENT_MIN_M = 1.0e-6
# surface_refine: 1 (uniform mesh; below 1 the surface would be coarser than the bulk) .. 64 (the grading zone is a
# third of the height: beyond 64 the mesh is all surface layer; tests and benches use 1 .. 16).
SURFACE_REFINE_MIN = 1.0
SURFACE_REFINE_MAX = 64.0
# Compressive strain of the tissue (load A: top_displacement_m / height_m; an indentation: depth / height, and
# depth / the tissue layer above a stone): the linear small-strain model is stated for strains up to 10 % (warned
# above, fem.guards), and refused above 30 %, where elements begin to invert (a 5 mm tissue indented 4 mm: 13 of
# 631 elements inverted) and the linear answer has no meaning.
STRAIN_WARN = 0.10
STRAIN_MAX = 0.30


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_load_a(scene: "Scene") -> None:
    """Load A's own limit, checked where load A is solved (fem.uniform, fem.uniform3d): the top moved down by
    ``analysis.top_displacement_m`` (default 5 mm, the study's) within (0, height) and at most STRAIN_MAX of the
    height. Not at load time: the other loads never use it, and a tissue thinner than 16.7 mm was refused by every
    command for a default the user never set. 0 is refused here: it loads nothing (every stress 0 Pa, the "peak" at
    an arbitrary point)."""
    d, h = scene.analysis.top_displacement_m, scene.tissue.height_m
    if not 0 < d < h:
        raise SceneError(f"analysis.top_displacement_m = {d!r} (load A; default {Analysis().top_displacement_m:g} "
                         f"when not given) must lie in (0, height_m = {h:g}) m, at most {STRAIN_MAX * h:.4g} m"
                         + (": 0 moves the top by nothing, so load A would load nothing" if d == 0 else ""))
    if d > STRAIN_MAX * h:
        raise SceneError(f"analysis.top_displacement_m = {d!r} (load A; default {Analysis().top_displacement_m:g} "
                         f"when not given) is {d / h:.0%} of the tissue height "
                         f"({h:g} m): the linear model allows at most {STRAIN_MAX:.0%} "
                         f"(top_displacement_m <= {STRAIN_MAX * h:.4g} m; it is stated for up to "
                         f"{STRAIN_WARN:.0%})")


def _check_positive(where: str, value) -> None:
    if not _is_number(value) or not math.isfinite(value) or value <= 0:
        raise SceneError(f"{where} must be a positive finite number, got {value!r}")


def _check_range(where: str, value, lo: float, hi: float, unit: str, why: str = "") -> None:
    _check_positive(where, value)
    if not lo <= value <= hi:
        raise SceneError(f"{where} = {value!r} is outside the allowed range [{lo:g}, {hi:g}] {unit}{why}")


def _check_modulus(where: str, value) -> None:
    _check_range(where, value, MODULUS_MIN_PA, MODULUS_MAX_PA, "Pa",
                 " (beyond it the stiffness and stresses leave double precision)")


def _check_length(where: str, value) -> None:
    _check_range(where, value, LENGTH_MIN_M, LENGTH_MAX_M, "m")


def _check_poisson(where: str, value) -> None:
    if not _is_number(value) or not (-1.0 < value < 0.5):
        raise SceneError(f"{where} must lie in (-1, 0.5), got {value!r}")


def validate(scene: Scene) -> None:
    t = scene.tissue
    _check_length("tissue.width_m", t.width_m)
    _check_length("tissue.height_m", t.height_m)
    _check_modulus("tissue.youngs_pa", t.youngs_pa)
    _check_poisson("tissue.poisson", t.poisson)
    if t.length_m is not None:
        _check_length("tissue.length_m", t.length_m)
        _validate_stones_3d(scene)
    else:
        _validate_stones_2d(scene)
    _validate_indenter(scene)
    _validate_analysis(scene)


def _check_stone_material(w: str, s: Stone) -> None:
    _check_length(f"{w}.diameter_m", s.diameter_m)
    _check_modulus(f"{w}.youngs_pa", s.youngs_pa)
    _check_poisson(f"{w}.poisson", s.poisson)


def _validate_stones_2d(scene: Scene) -> None:
    t = scene.tissue
    for i, s in enumerate(scene.stones):
        w = f"stone[{i}]"
        for name in ("x_m", "depth_m"):
            _check_positive(f"{w}.{name}", getattr(s, name))
        if s.y_m is not None:
            raise SceneError(f"{w}.y_m = {s.y_m!r} places a sphere in a 3D block, but the tissue has no length_m "
                             f"(a 2D section): give tissue.length_m for a 3D scene, or drop y_m")
        _check_stone_material(w, s)
        r = s.radius_m
        if _touches(s.x_m, r, t.width_m):
            raise SceneError(f"{w} (x_m={s.x_m}, diameter_m={s.diameter_m}) touches or leaves the tissue sideways "
                             f"(width_m={t.width_m})")
        if _touches(s.depth_m, r, t.height_m):
            raise SceneError(f"{w} (depth_m={s.depth_m}, diameter_m={s.diameter_m}) touches or leaves the tissue through "
                             f"the top or bottom (height_m={t.height_m})")
        for j in range(i):
            o = scene.stones[j]
            if math.hypot(s.x_m - o.x_m, s.depth_m - o.depth_m) <= (r + o.radius_m) * (1 + 1e-9):  # decimal inputs
                raise SceneError(f"{w} touches or overlaps stone[{j}]")


def _touches(centre_m: float, radius_m: float, size_m: float) -> bool:
    """Whether a stone's extent [centre - radius, centre + radius] reaches a face at 0 or size_m, within a relative
    1e-9 (as written in decimals, a stone touching a face is touching: 0.045 + 0.005 is below 0.05 in binary)."""
    tol = 1e-9 * size_m
    return centre_m - radius_m <= tol or centre_m + radius_m >= size_m - tol


def _validate_stones_3d(scene: Scene) -> None:
    t = scene.tissue
    for i, s in enumerate(scene.stones):
        w = f"stone[{i}]"
        if s.y_m is None:
            raise SceneError(f"{w}.y_m is missing: a 3D scene (tissue.length_m = {t.length_m!r}) places each "
                             f"sphere by x_m, y_m and depth_m (no default y_m is assumed)")
        for name in ("x_m", "y_m", "depth_m"):
            _check_positive(f"{w}.{name}", getattr(s, name))
        _check_stone_material(w, s)
        r = s.radius_m
        for name, lo_hi, extent in (("x_m", s.x_m, "width_m"), ("y_m", s.y_m, "length_m")):
            size = getattr(t, extent)
            if _touches(lo_hi, r, size):
                raise SceneError(f"{w} ({name}={lo_hi}, diameter_m={s.diameter_m}) touches or leaves the tissue sideways "
                                 f"({extent}={size})")
        if _touches(s.depth_m, r, t.height_m):
            raise SceneError(f"{w} (depth_m={s.depth_m}, diameter_m={s.diameter_m}) touches or leaves the tissue through "
                             f"the top or bottom (height_m={t.height_m})")
        for j in range(i):
            o = scene.stones[j]
            if math.dist((s.x_m, s.y_m, s.depth_m), (o.x_m, o.y_m, o.depth_m)) <= (r + o.radius_m) * (1 + 1e-9):
                raise SceneError(f"{w} touches or overlaps stone[{j}]")


def _validate_indenter(scene: Scene) -> None:
    t, ind = scene.tissue, scene.indenter
    shapes = ("sphere", "flat") if scene.is_3d else ("cylinder", "flat")
    if ind.shape not in shapes:
        kind = (f"a 3D scene (tissue.length_m = {t.length_m!r})" if scene.is_3d
                else "a 2D scene (no tissue.length_m)")
        raise SceneError(f"indenter.shape must be {' or '.join(map(repr, shapes))} in {kind}, got {ind.shape!r}")
    _check_length("indenter.radius_m", ind.radius_m)
    if ind.radius_m > t.width_m / 2:
        raise SceneError(f"indenter.radius_m = {ind.radius_m!r} must be at most half the tissue width "
                         f"({t.width_m / 2:g} m): a wider tip does not fit on the surface")
    if scene.is_3d and ind.radius_m > t.length_m / 2:
        raise SceneError(f"indenter.radius_m = {ind.radius_m!r} must be at most half the tissue length "
                         f"({t.length_m / 2:g} m): a wider tip does not fit on the surface")
    _check_length("indenter.thickness_m", ind.thickness_m)
    if scene.is_3d and ind.thickness_m != Indenter.thickness_m:
        raise SceneError(f"indenter.thickness_m = {ind.thickness_m!r} is a 2D tip's out-of-plane length; a 3D tip "
                         f"(a {ind.shape}) has none: drop it")
    if ind.youngs_pa is not None:
        _check_modulus("indenter.youngs_pa", ind.youngs_pa)
    _check_poisson("indenter.poisson", ind.poisson)
    if ind.shape == "flat" and ind.youngs_pa is not None:
        rho = _tip_relative_compliance(scene)
        if rho >= ELASTIC_TIP_NEGLIGIBLE:
            round_tip = "sphere" if scene.is_3d else "cylinder"
            raise SceneError(f"indenter.youngs_pa = {ind.youngs_pa!r} with indenter.shape = 'flat': an elastic flat "
                             f"punch is not modelled (its edge is singular), and this one is too soft to be taken as "
                             f"rigid (its deformation would change the force by about {rho:.2g} of it, Hertz "
                             f"estimate; up to {ELASTIC_TIP_NEGLIGIBLE:g} is neglected); give no youngs_pa (rigid), a "
                             f"modulus at least {ind.youngs_pa * rho / ELASTIC_TIP_NEGLIGIBLE:.3g} Pa, or shape = "
                             f"'{round_tip}'")


# An elastic tip that would change the force by less than this is taken as rigid: fem.tip.TIP_TOLERANCE (the same
# value, tested; fem.tip imports this module)
ELASTIC_TIP_NEGLIGIBLE = 1e-3


def tip_taken_as_rigid(scene: Scene) -> bool:
    """Whether fem models the scene's tip as rigid (fem.tip.treated_as_rigid's "auto", without importing fem.tip):
    no modulus given, or one that changes the force by less than ELASTIC_TIP_NEGLIGIBLE."""
    return scene.indenter.youngs_pa is None or _tip_relative_compliance(scene) < ELASTIC_TIP_NEGLIGIBLE


def _tip_relative_compliance(scene: Scene) -> float:
    """fem.tip.rigid_tip_bound (the same formula, tested): the relative change of the force from treating the
    scene's elastic tip as rigid."""
    t, ind = scene.tissue, scene.indenter
    if scene.analysis.plane == "strain":
        return t.youngs_pa * (1 - ind.poisson ** 2) / (ind.youngs_pa * (1 - t.poisson ** 2))
    return t.youngs_pa / ind.youngs_pa


def _validate_analysis(scene: Scene) -> None:
    t = scene.tissue
    a = scene.analysis
    if a.plane not in ("strain", "stress"):
        raise SceneError(f"analysis.plane must be 'strain' or 'stress', got {a.plane!r}")
    if a.order not in (1, 2):
        raise SceneError(f"analysis.order must be 1 or 2, got {a.order!r}")
    if a.formulation not in ("displacement", "mixed"):
        raise SceneError(f"analysis.formulation must be 'displacement' or 'mixed', got {a.formulation!r}")
    if a.formulation == "mixed" and (a.order != 2 or a.plane != "strain"):
        raise SceneError("analysis.formulation='mixed' (Taylor-Hood P2/P1) needs order = 2 and plane = 'strain' "
                         f"(got order = {a.order!r}, plane = {a.plane!r}); plane stress does not lock")
    _check_positive("analysis.mesh_size_m", a.mesh_size_m)
    _check_range("analysis.surface_refine", a.surface_refine, SURFACE_REFINE_MIN, SURFACE_REFINE_MAX, "",
                 " (the surface element size is mesh_size_m / surface_refine)")
    if a.mesh_size_m > min(t.width_m, t.height_m) / 2:
        side = "height_m" if t.height_m <= t.width_m else "width_m"
        raise SceneError(f"analysis.mesh_size_m={a.mesh_size_m:g} is larger than half the tissue's {side} "
                         f"({min(t.width_m, t.height_m):g} m): give [analysis] mesh_size_m <= "
                         f"{min(t.width_m, t.height_m) / 2:g} (when not given, it is the scene's default)")
    if a.mesh_size_m / a.surface_refine < ELEMENT_MIN_M:
        raise SceneError(f"analysis.mesh_size_m / surface_refine = {a.mesh_size_m:g} / {a.surface_refine:g} m = "
                         f"{a.mesh_size_m / a.surface_refine:.3g} m: the finest element must be at least "
                         f"{ELEMENT_MIN_M:g} m (1 um); increase mesh_size_m or lower surface_refine")
    d = a.top_displacement_m
    if not _is_number(d) or not math.isfinite(d) or not d >= 0:
        raise SceneError(f"analysis.top_displacement_m must be a finite number >= 0 (m), got {d!r}")
    if scene.is_3d:
        if a.plane != "strain":
            raise SceneError(f"analysis.plane = {a.plane!r} is 2D only (a 3D block has no plane assumption): drop it")
        if a.formulation != "displacement":
            raise SceneError(f"analysis.formulation = {a.formulation!r} is 2D only; a 3D scene uses "
                             f"'displacement' (P1/P2 tetrahedra)")
        if a.mesh_size_m > t.length_m / 2:
            raise SceneError(f"analysis.mesh_size_m={a.mesh_size_m:g} is larger than half the tissue's length_m "
                             f"({t.length_m / 2:g} m): give [analysis] mesh_size_m <= {t.length_m / 2:g} (when not "
                             f"given, it is the scene's default)")
        if a.patch_m is not None:
            _check_length("analysis.patch_m", a.patch_m)
            if a.patch_m > min(t.width_m, t.length_m):
                raise SceneError(f"analysis.patch_m = {a.patch_m!r} is wider than the top face "
                                 f"({min(t.width_m, t.length_m):g} m, the smaller of width_m and length_m)")
            if a.patch_m < 2 * scene.indenter.radius_m:
                raise SceneError(f"analysis.patch_m = {a.patch_m!r} is narrower than the tip (2 x indenter.radius_m "
                                 f"= {2 * scene.indenter.radius_m:g} m): the tip's footprint must fit on the probed "
                                 f"patch; give patch_m >= {2 * scene.indenter.radius_m:g} m or a smaller tip")
        if a.grade is not None:
            _check_range("analysis.grade", a.grade, 0.05, 2.0, "",
                         " (the element size's growth per unit distance from the probed patch and the stones)")
    elif a.patch_m is not None or a.grade is not None:
        which = "patch_m" if a.patch_m is not None else "grade"
        raise SceneError(f"analysis.{which} = {getattr(a, which)!r} applies to a 3D block (its probed patch and "
                         f"grading); a 2D scene (no tissue.length_m) has none: drop it or give tissue.length_m")


# ---------------------------------------------------------------------------------------------------------------
# TOML

_SECTIONS = {"tissue": Tissue, "stone": Stone, "indenter": Indenter, "analysis": Analysis}


def _build(cls, table, where: str):
    if not isinstance(table, dict):
        raise SceneError(f"[{where}] must be a table, got {type(table).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise SceneError(f"unknown key(s) in [{where}]: {', '.join(map(str, unknown))} (known: {', '.join(fields)})")
    kwargs = {}
    for k, v in table.items():
        if k in ("shape", "plane", "formulation"):
            if not isinstance(v, str):
                raise SceneError(f"{where}.{k} must be a string, got {type(v).__name__}")
        elif k == "order":
            if not isinstance(v, int) or isinstance(v, bool):
                raise SceneError(f"{where}.{k} must be an integer, got {type(v).__name__}")
        elif not isinstance(v, (int, float)) or isinstance(v, bool):
            raise SceneError(f"{where}.{k} must be a number, got {type(v).__name__} {v!r}")
        else:
            try:
                v = float(v)
            except OverflowError:     # an integer beyond double precision
                raise SceneError(f"{where}.{k} = {v} is beyond double precision") from None
        kwargs[k] = v
    required = [f.name for f in fields.values() if f.init and f.default is dataclasses.MISSING
                and f.default_factory is dataclasses.MISSING]
    missing = [k for k in required if k not in kwargs]
    if missing:
        raise SceneError(f"{where}.{missing[0]} is missing (required in [{where}]: {', '.join(required)})")
    return cls(**kwargs)


REQUIRED_TISSUE = ("width_m", "height_m", "youngs_pa", "poisson")


def from_dict(d: dict, default_name: str = "scene") -> Scene:
    """A scene from a parsed TOML file or ``Scene.to_dict()``. The [tissue] table and its four fields are required
    (a file without them would otherwise silently describe the default tissue); stones, [indenter] and [analysis]
    may be left out (no stones, the default tip and analysis options; a block's file: ``load_toml``)."""
    if not isinstance(d, dict):
        raise SceneError(f"a scene must be a table, got {type(d).__name__}")
    unknown = sorted(set(d) - {"name", "truth", *_SECTIONS})    # [truth]: the simulator's (robot.truth), skipped
    if unknown:
        raise SceneError(f"unknown top-level key(s): {', '.join(map(str, unknown))} "
                         f"(known: name, tissue, stone, indenter, analysis, truth)")
    name = d.get("name", default_name)
    if not isinstance(name, str):
        raise SceneError(f"name must be a string, got {type(name).__name__}")
    if not (name.strip() and name.isprintable()):
        raise SceneError(f"name = {name[:80]!r}{'...' if len(name) > 80 else ''}: give printable characters, not "
                         f"blank, no line breaks or control codes (the name is printed in the commands' lines)")
    stones = d.get("stone", [])
    if isinstance(stones, dict):
        stones = [stones]
    if not isinstance(stones, list):
        raise SceneError("stone must be an array of tables ([[stone]])")
    tissue_table = d.get("tissue", {})
    tissue = _build(Tissue, tissue_table, "tissue")
    built = dict(stones=tuple(_build(Stone, s, f"stone[{i}]") for i, s in enumerate(stones)),
                 indenter=_build(Indenter, d.get("indenter", {}), "indenter"),
                 analysis=_build(Analysis, d.get("analysis", {}), "analysis"))
    if "tissue" not in d:
        raise SceneError(f"the scene has no [tissue] table: give [tissue] with {', '.join(REQUIRED_TISSUE)} "
                         f"(no default tissue is assumed)")
    missing = [k for k in REQUIRED_TISSUE if k not in tissue_table]
    if missing:
        raise SceneError(f"[tissue] lacks {', '.join(missing)} (required: {', '.join(REQUIRED_TISSUE)}; no default "
                         f"is assumed)")
    return Scene(name=name, tissue=tissue, **built)


def load_toml(path: str | Path) -> Scene:
    """A scene file. A block's (``tissue.length_m``) that leaves out its tip or mesh gets a block's
    (``block_file_defaults``), not the dataclasses' defaults, which are a 2D section's."""
    import tomllib  # lazy: TOML scenes only (4 ms of a built-in scene's 0.2 s command; issue 19)
    path = Path(path)
    text = read_user_text(path, "scene")
    try:
        d = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML: {e}") from None
    except RecursionError:
        raise SceneError(f"{path}: not valid TOML: {NESTED_TOO_DEEP}") from None
    return from_dict(block_file_defaults(d), default_name=path.stem)


# A block's scene file leaves out what a block needs (load_toml): the 3D tip, and block3d's mesh (its element sizes
# and grading, chosen by the convergence study in docs/bench_3d.md). The probed patch: the whole top face up to 50 mm across
# (block3d's probed side; a block 50 x 60 mm: 9,857 patch nodes), else a centred square with a 10 mm margin, at
# most 50 mm (a 70 mm face whole: 16,217 nodes, beyond fem.contact3d.MAX_PATCH_NODES).
BLOCK_FILE_PATCH_MAX_M = 0.050
BLOCK_FILE_PATCH_MARGIN_M = 0.010


def block_file_defaults(d: dict) -> dict:
    """``d`` (a parsed scene file) with what a block's file leaves out filled in; anything else as it is."""
    tissue, indenter, analysis = d.get("tissue"), d.get("indenter", {}), d.get("analysis", {})
    if not (isinstance(tissue, dict) and isinstance(indenter, dict) and isinstance(analysis, dict)):
        return d                           # from_dict says what is wrong
    W, L = tissue.get("width_m"), tissue.get("length_m")
    if L is None or not (_is_number(W) and _is_number(L)) or not (math.isfinite(W) and math.isfinite(L)):
        return d
    fill = {"mesh_size_m": BLOCK3D_ANALYSIS.mesh_size_m, "surface_refine": BLOCK3D_ANALYSIS.surface_refine,
            "grade": BLOCK3D_ANALYSIS.grade}
    side = min(W, L)
    if side > BLOCK_FILE_PATCH_MAX_M:
        fill["patch_m"] = min(side - 2 * BLOCK_FILE_PATCH_MARGIN_M, BLOCK_FILE_PATCH_MAX_M)
    return {**d, "indenter": {"shape": "sphere", **indenter}, "analysis": fill | analysis}


def dump_toml(scene: Scene) -> str:
    """A scene file that ``load_toml`` reads back equal. ValueError for a block whose patch or grading is unset: a
    file cannot say "unset" (TOML has no null), and a block's file without them means ``block_file_defaults``'."""
    if scene.is_3d and (scene.analysis.grade is None or scene.analysis.patch_m is None):
        back = from_dict(block_file_defaults(scene.to_dict()), scene.name)
        if back != scene:
            raise ValueError(f"scene {scene.name!r}: a block with analysis.patch_m or analysis.grade unset cannot be "
                             f"written as a file (a file without them gets a block file's defaults); set them")

    def val(v):
        return json.dumps(v) if isinstance(v, str) else repr(v)
    d = scene.to_dict()
    lines = [f"name = {val(d['name'])}"]
    for sec in ("tissue", "indenter", "analysis"):
        lines.append(f"\n[{sec}]")
        lines += [f"{k} = {val(v)}" for k, v in d[sec].items()]
    for s in d["stone"]:
        lines.append("\n[[stone]]")
        lines += [f"{k} = {val(v)}" for k, v in s.items()]
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------------------------
# Built-in scenes (the published study)

def _paper(name: str, x_m: float = 0.035, depth_m: float = 0.025, diameter_m: float = 0.015) -> Scene:
    return Scene(name=name, stones=(Stone(x_m=x_m, depth_m=depth_m, diameter_m=diameter_m),),
                 indenter=Indenter(youngs_pa=60.0e6))


BUILTIN = {
    "paper": lambda: _paper("paper"),
    "paper-left": lambda: _paper("paper-left", x_m=0.020),
    "paper-right": lambda: _paper("paper-right", x_m=0.050),
    "paper-deep": lambda: _paper("paper-deep", depth_m=0.040, diameter_m=0.010),
    "healthy": lambda: Scene(name="healthy", indenter=Indenter(youngs_pa=60.0e6)),
}

# 3D (issue 15): a 70 x 70 x 50 mm block, the study's tissue and stone, a spherical 5 mm tip of 60 MPa; the probed
# patch is the central 50 x 50 mm (a 40 x 40 mm raster plus the tip radius on each side). The mesh: P2, 1.2 mm on the
# patch, growing by 0.2 per unit distance to 9.6 mm: 0.8 times the first default (12 mm, grade 0.25) in every size,
# the coarsest of the uniformly refined family within 1 % of the converged force at every benchmark waypoint with a
# margin (0.69 % at worst; the first default: 1.36 %); docs/bench_3d.md's convergence table, bench/bench_3d.py.
BLOCK3D_ANALYSIS = Analysis(order=2, mesh_size_m=0.0096, surface_refine=8.0, patch_m=0.050, grade=0.2)


def _block3d(name: str, stone: bool = True, x_m: float = 0.035, y_m: float = 0.035, depth_m: float = 0.025,
             diameter_m: float = 0.015) -> Scene:
    stones = (Stone(x_m=x_m, y_m=y_m, depth_m=depth_m, diameter_m=diameter_m),) if stone else ()
    return Scene(name=name, tissue=Tissue(length_m=0.070), stones=stones,
                 indenter=Indenter(shape="sphere", radius_m=0.005, youngs_pa=60.0e6), analysis=BLOCK3D_ANALYSIS)


BUILTIN.update({
    "block3d": lambda: _block3d("block3d"),
    "block3d-healthy": lambda: _block3d("block3d-healthy", stone=False),
    "block3d-left": lambda: _block3d("block3d-left", x_m=0.020),          # stone moved in x
    "block3d-front": lambda: _block3d("block3d-front", y_m=0.020),        # stone moved in y
    "block3d-deep": lambda: _block3d("block3d-deep", depth_m=0.040, diameter_m=0.010),
})


def load(spec: str | Path | Scene) -> Scene:
    """A scene from a built-in name, a TOML path, or a Scene (returned as is)."""
    if isinstance(spec, Scene):
        return spec
    s = str(spec)
    if s in BUILTIN:
        return BUILTIN[s]()
    p = Path(s)
    if p.suffix == ".toml" or p.exists():
        if not p.exists():
            raise SceneError(f"scene file {p} does not exist")
        return load_toml(p)
    raise SceneError(f"unknown scene {s!r}: give a TOML file or one of {', '.join(BUILTIN)}")
