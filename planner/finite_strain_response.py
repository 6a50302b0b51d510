"""The prior's finite-strain correction: how much harder a neo-Hookean tissue with the PRIOR's parameters pushes
back than fem's linear model, per probe position and depth. The localizer's finite-strain term (planner.localize)
uses its shape with a fitted amplitude; nothing here reads a truth.

    g(x, d) = F_neo-Hookean(x, d) / F_linear(x, d) - 1            (the prior: nominal tissue, no stones)

from fem's own finite-strain indentation of the prior (fem.hypertruth.HyperelasticForce.ratio: one load-stepped
sweep in depth per position on the prior's correction mesh, the linear force on the same mesh). On the paper
tissue at 4 mm, g is +2.8 % in the middle and +17 % 5 mm from a side (the free sides soften the linear response
more than the finite-strain one); it grows almost linearly with depth and does not depend on the modulus (both
forces are proportional to E at a fixed Poisson ratio, the tip being rigid).

The table: sweeps at ``X_NODES_TIP_RADII`` tip radii from the left side, then every tip radius, up to the middle
(the prior is mirror symmetric: fem.hyperindent's supports make mirror images agree to 5e-5), at the sweep's depths
(fem.hypertruth.sweep_depths: every 0.5 mm to 0.98 tip radii). Between the positions, monotone cubic (PCHIP)
interpolation in x: against direct sweeps at 8 positions between the paper's nodes it errs by at most 0.23 % of
the force (1 mm deep at 11.25 mm; typically below 0.1 %: about what the mesh's contact nodes make g scatter by from
one position to the next). Nearer a side than the first node g is held at that node's (the planner keeps probes 5
mm from the sides; a sweep 2 mm from the side folds the tissue over at 2 mm deep); linear in depth between the
sweep's depths and extrapolated linearly beyond the last (g is close to linear in depth); a position whose sweep
stopped early is continued the same way from the depths it reached.

Cost: one sweep per node (11 for the paper prior: about 20 s of CPU on this machine, cold; 35 s before session 58's
CHOLMOD reuse in fem.hyperindent) and the correction mesh's linear model. The table is kept on disk (fem.diskcache,
kind ``hypershape``, keyed by the prior's correction scene, the nodes and depths, ``FORMAT`` and the code of fem's
finite-strain and linear models); a table for the built-in paper prior is shipped in planner/data/ (the same name;
used when the disk cache has none), so the paper prior costs nothing cold either.
"""
from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator

from core.arrays import clip
from fem import diskcache
from fem.hypertruth import HyperelasticForce, correction_scene, sweep_depths
from fem.scene_mesh import code_version, sources_version
from fem.tip import contact_scene, tip_too_soft

X_NODES_TIP_RADII = (0.7, 1.0, 1.3, 1.6, 2.0, 2.5, 3.0)    # from the side, then every tip radius to the middle
MIN_NODES = 3              # fewer usable positions (a section narrower than a few tip radii): no finite-strain term
FORMAT = 1                 # bump when what the table holds changes (the fem code's own version is in the key)
KIND = "hypershape"
SHIPPED = Path(__file__).resolve().parent / "data"
# the shape is built and kept at this tissue modulus whatever the prior's: F_neo-Hookean / F_linear does not depend
# on it (a rigid tip, no stones, both solids' moduli proportional to E: the displacements under a given indentation
# are the same; the fem's tolerances are relative). Measured on a coarse paper section at 2500 and 6000 Pa: g the
# same to 4e-14 (max |g| 0.57). Before session 44 every new modulus rebuilt it: 26 s for the paper section
SHAPE_YOUNGS_PA = 2500.0

_MEM: dict[str, "FiniteStrainShape | None"] = {}


@dataclass(frozen=True)
class FiniteStrainShape:
    """g = F_neo-Hookean / F_linear - 1 of a prior at nodes (x from the left side to the middle, depth from 0)."""
    width_m: float
    x_m: np.ndarray            # (nx,) node positions, increasing, <= width / 2
    depth_m: np.ndarray        # (nd,) depth nodes, increasing, the first 0
    g: np.ndarray              # (nx, nd) the correction at the nodes (0 at depth 0)
    sweeps_s: float = 0.0      # what the sweeps cost when they were computed (their time_s, summed)

    def at(self, x_m) -> "FiniteStrainRows":
        """The correction at fixed probe positions ``x_m`` (mirrored into the left half, held at the first node
        nearer a side), as a function of depth."""
        x = np.clip(np.asarray(x_m, float), 0.0, self.width_m)
        x = np.minimum(x, self.width_m - x)
        x = np.clip(x, self.x_m[0], self.x_m[-1])
        rows = PchipInterpolator(self.x_m, self.g, axis=0)(x)
        return FiniteStrainRows(np.atleast_2d(rows), self.depth_m)

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {"width_m": np.float64(self.width_m), "x_m": self.x_m, "depth_m": self.depth_m, "g": self.g,
                "sweeps_s": np.float64(self.sweeps_s)}

    @staticmethod
    def from_arrays(d: dict[str, np.ndarray]) -> "FiniteStrainShape":
        x, dep, g = (np.array(d[k], float) for k in ("x_m", "depth_m", "g"))
        if g.shape != (len(x), len(dep)) or len(x) < MIN_NODES or np.any(np.diff(x) <= 0) or np.any(np.diff(dep) <= 0):
            raise ValueError("inconsistent finite-strain shape arrays")
        if not np.isfinite(g).all() or np.any(g[:, 1:] <= -1.0):
            raise ValueError("a finite-strain shape with a neo-Hookean force of 0 or less (g <= -1)")
        return FiniteStrainShape(float(d["width_m"]), x, dep, g, float(d["sweeps_s"]))


@dataclass(frozen=True)
class FiniteStrainRows:
    """g at fixed probes as a function of each probe's depth: ``g(depth_m)`` (one depth per probe)."""
    rows: np.ndarray           # (n, nd)
    depth_m: np.ndarray        # (nd,)

    def g(self, depth_m) -> np.ndarray:
        d = np.asarray(depth_m, float)
        nodes = self.depth_m
        k = clip(np.searchsorted(nodes, d) - 1, 0, len(nodes) - 2)     # beyond the ends: the end segments
        w = (d - nodes[k]) / (nodes[k + 1] - nodes[k])
        n = np.arange(len(d))
        return np.where(d > 0, (1 - w) * self.rows[n, k] + w * self.rows[n, k + 1], 0.0)

    def slope(self, depth_m) -> np.ndarray:
        """d g / d depth at each probe's depth (the segment's slope; 0 out of contact)."""
        d = np.asarray(depth_m, float)
        nodes = self.depth_m
        k = clip(np.searchsorted(nodes, d) - 1, 0, len(nodes) - 2)
        n = np.arange(len(d))
        return np.where(d > 0, (self.rows[n, k + 1] - self.rows[n, k]) / (nodes[k + 1] - nodes[k]), 0.0)


def unsupported(prior) -> str:
    """Why fem's finite-strain model cannot give this prior's correction ("" when it can)."""
    if prior.is_3d:
        return "the finite-strain model is 2D (a plane-strain section)"
    if prior.analysis.plane != "strain":
        return f"the finite-strain model is plane strain; the prior's analysis.plane is {prior.analysis.plane!r}"
    if tip_too_soft(prior):
        return "the finite-strain model needs a rigid-treated tip"
    if 0.5 * prior.tissue.width_m < X_NODES_TIP_RADII[MIN_NODES - 1] * prior.indenter.radius_m:
        return "the section is too narrow for the tip"
    return ""


def x_nodes(prior) -> np.ndarray:
    """The sweep positions: ``X_NODES_TIP_RADII`` tip radii from the left side, then every tip radius, and the
    middle."""
    R, half = prior.indenter.radius_m, 0.5 * prior.tissue.width_m
    x = list(np.asarray(X_NODES_TIP_RADII) * R)
    while x[-1] + R < half - 0.25 * R:
        x.append(x[-1] + R)
    x = [v for v in x if v < half - 0.25 * R] + [half]
    return np.round(np.array(x), 9)


def _spec(prior) -> dict:
    code = sources_version(("neohooke.py", "finite_strain.py", "hyperindent.py", "hypertruth.py"),
                           f"linear {code_version()}")
    return {"scene": correction_scene(prior).key(), "x_m": [repr(float(v)) for v in x_nodes(prior)],
            "depths": [repr(float(d)) for d in sweep_depths(prior)], "format": FORMAT, "fem": code}


def build_shape(prior) -> FiniteStrainShape:
    """The table from fem's sweeps of the prior (each from the disk cache when there, else computed)."""
    hf = HyperelasticForce(prior)
    depths = np.concatenate([[0.0], sweep_depths(prior)])
    xs, rows = [], []
    for x in x_nodes(prior):
        d, r = hf.ratio(float(x))
        if len(d) < 3:            # the sweep stopped before its second depth: no usable shape there
            continue
        g = r - 1.0
        if np.any(g[1:] <= -1.0) or not np.isfinite(g).all():   # a force of 0 or less where the linear is positive:
            continue                                            # not a shape (1 + a g must stay positive)
        k = np.clip(np.searchsorted(d, depths) - 1, 0, len(d) - 2)
        w = (depths - d[k]) / (d[k + 1] - d[k])
        rows.append((1 - w) * g[k] + w * g[k + 1])        # at the common depths; continued linearly past the last
        xs.append(float(x))
    if len(xs) < MIN_NODES:
        raise ValueError(f"the finite-strain sweeps reached depth at only {len(xs)} positions")
    return FiniteStrainShape(prior.tissue.width_m, np.array(xs), depths, np.array(rows),
                             sweeps_s=float(sum(sw.time_s for sw in hf.sweeps.values())))


def at_shape_modulus(prior):
    """The prior as its shape is built, keyed and kept: its tissue at SHAPE_YOUNGS_PA and an elastic tip's modulus
    scaled with it (the ratio of the two, which fem's rigid-or-elastic decision and the finite-strain model's
    refusal read, unchanged: g is then the same for every tissue modulus, an elastic tip's included), and a tip fem
    treats as rigid without its modulus (fem.tip.contact_scene). Both forces of the ratio take such a tip as rigid
    (the finite-strain model's tip always is; the linear model drops it through the same contact_scene), so the
    study's 60 MPa tip and a scene's default rigid one share one table: until session 58 a scene with the paper's
    tissue and no tip modulus built its own (35 s), the same numbers under another key, and an elastic tip kept its
    modulus at 2500 Pa, where the decision could come out otherwise."""
    prior = contact_scene(prior)
    ind = prior.indenter
    if ind.youngs_pa is not None:          # (to 12 digits: the same ratio, the same key, whatever the rounding)
        scaled = ind.youngs_pa / prior.tissue.youngs_pa * SHAPE_YOUNGS_PA
        ind = dataclasses.replace(ind, youngs_pa=float(f"{scaled:.12g}"))
    return dataclasses.replace(prior, tissue=dataclasses.replace(prior.tissue, youngs_pa=SHAPE_YOUNGS_PA),
                               indenter=ind)


def prior_finite_strain(prior, build: bool = True) -> FiniteStrainShape | None:
    """The prior's finite-strain shape: from memory, the disk cache or planner/data, else built (``build``) and
    written to the disk cache; None when fem's finite-strain model does not cover the prior (``unsupported``) or
    no table exists and ``build`` is False. A scene with stones is refused (ValueError): the shape is the prior's,
    never a truth's."""
    if prior.stones:
        raise ValueError("prior_finite_strain() takes the prior scene (no stones): the localizer must not see the "
                         "truth")
    if unsupported(prior):
        return None
    prior = at_shape_modulus(prior)
    key = prior.key()
    if key in _MEM:
        return _MEM[key]
    spec = _spec(prior)
    shape = diskcache.load(KIND, spec, FiniteStrainShape.from_arrays)
    if shape is None:
        shipped = diskcache.read(SHIPPED / diskcache.entry_path(KIND, spec).name)
        if shipped is not None:
            try:
                shape = FiniteStrainShape.from_arrays(shipped)
            except (KeyError, ValueError):
                shape = None
    if shape is None and build:
        try:
            shape = build_shape(prior)
        except ValueError as e:       # fem's sweeps did not reach depth on enough positions: no term, said once
            warnings.warn(f"the localizer runs without its finite-strain term for this prior: {e}", stacklevel=2)
            _MEM[key] = None          # (once per process: each fit asked again, and built and warned again)
            return None
        if diskcache.enabled():
            diskcache.write(diskcache.entry_path(KIND, spec), shape.to_arrays())
    if shape is not None:
        _MEM[key] = shape
    return shape
