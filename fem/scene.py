"""Scenes: the tissue section, the stones in it, the probe tip and analysis options.

All quantities are SI (m, Pa). The 2D section lies in the x-y plane: x from the left edge (0 .. width_m),
y up from the bottom edge (0 .. height_m). A stone's ``depth_m`` is the depth of its centre below the top surface.

A scene plays two roles in a simulated run (see docs/architecture.md, "Truth and belief"): the simulator holds the full scene
(the truth), the planner and the localizer hold ``scene.prior()`` — the same tissue with its stones removed.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path


class SceneError(ValueError):
    """A scene description that cannot be used; the message names the offending field."""


@dataclass(frozen=True)
class Tissue:
    width_m: float = 0.070
    height_m: float = 0.050
    youngs_pa: float = 2500.0
    poisson: float = 0.4


@dataclass(frozen=True)
class Stone:
    x_m: float
    depth_m: float
    diameter_m: float
    youngs_pa: float = 5.0e9
    poisson: float = 0.3

    @property
    def radius_m(self) -> float:
        return 0.5 * self.diameter_m


@dataclass(frozen=True)
class Indenter:
    shape: str = "cylinder"          # "cylinder" (circle of radius_m) or "flat" (punch of half-width radius_m)
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

    def prior(self) -> Scene:
        """What a surgeon knows before probing: the tissue, no stones."""
        return dataclasses.replace(self, name=f"{self.name}-prior", stones=())

    def with_analysis(self, **changes) -> Scene:
        return dataclasses.replace(self, analysis=dataclasses.replace(self.analysis, **changes))

    def with_stones(self, stones) -> Scene:
        return dataclasses.replace(self, stones=tuple(stones))

    def to_dict(self) -> dict:
        d = {"name": self.name, "tissue": dataclasses.asdict(self.tissue),
             "stone": [dataclasses.asdict(s) for s in self.stones],
             "indenter": {k: v for k, v in dataclasses.asdict(self.indenter).items() if v is not None},
             "analysis": dataclasses.asdict(self.analysis)}
        return d

    def key(self) -> str:
        """A content hash: equal scenes (whatever their name) give equal keys."""
        d = self.to_dict()
        d.pop("name")
        if d["analysis"].get("formulation") == "displacement":   # keys from before the field existed stay valid
            del d["analysis"]["formulation"]
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def _check_positive(where: str, value) -> None:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value) or value <= 0:
        raise SceneError(f"{where} must be a positive finite number, got {value!r}")


def _check_poisson(where: str, value) -> None:
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not (-1.0 < value < 0.5):
        raise SceneError(f"{where} must lie in (-1, 0.5), got {value!r}")


def validate(scene: Scene) -> None:
    t = scene.tissue
    _check_positive("tissue.width_m", t.width_m)
    _check_positive("tissue.height_m", t.height_m)
    _check_positive("tissue.youngs_pa", t.youngs_pa)
    _check_poisson("tissue.poisson", t.poisson)
    for i, s in enumerate(scene.stones):
        w = f"stone[{i}]"
        for name in ("x_m", "depth_m", "diameter_m", "youngs_pa"):
            _check_positive(f"{w}.{name}", getattr(s, name))
        _check_poisson(f"{w}.poisson", s.poisson)
        r = s.radius_m
        if s.x_m - r <= 0 or s.x_m + r >= t.width_m:
            raise SceneError(f"{w} (x_m={s.x_m}, diameter_m={s.diameter_m}) leaves the tissue sideways "
                             f"(width_m={t.width_m})")
        if s.depth_m - r <= 0 or s.depth_m + r >= t.height_m:
            raise SceneError(f"{w} (depth_m={s.depth_m}, diameter_m={s.diameter_m}) leaves the tissue through "
                             f"the top or bottom (height_m={t.height_m})")
        for j in range(i):
            o = scene.stones[j]
            if math.hypot(s.x_m - o.x_m, s.depth_m - o.depth_m) <= r + o.radius_m:
                raise SceneError(f"{w} touches or overlaps stone[{j}]")
    ind = scene.indenter
    if ind.shape not in ("cylinder", "flat"):
        raise SceneError(f"indenter.shape must be 'cylinder' or 'flat', got {ind.shape!r}")
    _check_positive("indenter.radius_m", ind.radius_m)
    _check_positive("indenter.thickness_m", ind.thickness_m)
    if ind.youngs_pa is not None:
        _check_positive("indenter.youngs_pa", ind.youngs_pa)
    _check_poisson("indenter.poisson", ind.poisson)
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
    _check_positive("analysis.surface_refine", a.surface_refine)
    if a.mesh_size_m > min(t.width_m, t.height_m) / 2:
        raise SceneError(f"analysis.mesh_size_m={a.mesh_size_m} is larger than half the tissue")
    if not isinstance(a.top_displacement_m, (int, float)) or not (0 <= a.top_displacement_m < t.height_m):
        raise SceneError(f"analysis.top_displacement_m must lie in [0, height_m), got {a.top_displacement_m!r}")


# ---------------------------------------------------------------------------------------------------------------
# TOML

_SECTIONS = {"tissue": Tissue, "stone": Stone, "indenter": Indenter, "analysis": Analysis}


def _build(cls, table, where: str):
    if not isinstance(table, dict):
        raise SceneError(f"[{where}] must be a table, got {type(table).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise SceneError(f"unknown key(s) in [{where}]: {', '.join(unknown)} (known: {', '.join(fields)})")
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
            v = float(v)
        kwargs[k] = v
    try:
        return cls(**kwargs)
    except TypeError as e:  # a required field missing
        raise SceneError(f"[{where}]: {e}") from None


def from_dict(d: dict, default_name: str = "scene") -> Scene:
    unknown = sorted(set(d) - {"name", *_SECTIONS})
    if unknown:
        raise SceneError(f"unknown top-level key(s): {', '.join(unknown)} "
                         f"(known: name, tissue, stone, indenter, analysis)")
    name = d.get("name", default_name)
    if not isinstance(name, str):
        raise SceneError(f"name must be a string, got {type(name).__name__}")
    stones = d.get("stone", [])
    if isinstance(stones, dict):
        stones = [stones]
    if not isinstance(stones, list):
        raise SceneError("stone must be an array of tables ([[stone]])")
    return Scene(name=name,
                 tissue=_build(Tissue, d.get("tissue", {}), "tissue"),
                 stones=tuple(_build(Stone, s, f"stone[{i}]") for i, s in enumerate(stones)),
                 indenter=_build(Indenter, d.get("indenter", {}), "indenter"),
                 analysis=_build(Analysis, d.get("analysis", {}), "analysis"))


def load_toml(path: str | Path) -> Scene:
    path = Path(path)
    try:
        d = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML: {e}") from None
    return from_dict(d, default_name=path.stem)


def dump_toml(scene: Scene) -> str:
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
