"""Option values and output paths, checked before any work (issue 13).

Numeric options: argparse ``type=`` functions (``finite_float``, ``positive_float``, ``float_range(lo, hi)``,
``int_range(lo, hi)``). A bad value ends in one line, ``prog: error: argument --opt: message (see prog --help)``
(``app.parser.Parser``: argparse without its usage block) and exit 2;
the message gives the value and what is allowed. Cross-option rules (a minimum below a limit, a budget above the
waypoints) are checked by the commands with ``UsageError``.

Scenes: ``load_scene`` (fem.scene.load with unreadable files named in one line).

Output paths: ``check_output_file`` / ``check_output_dir`` refuse, before the computation, a file option pointing at
a directory, a directory option pointing at a file, and a parent that cannot be created or written; they create
nothing. ``refuse_measured`` (also part of ``check_output_file``) refuses an output path that would overwrite a
run's measured files.
"""
from __future__ import annotations

import argparse
import errno
import ipaddress
import math
import os
from pathlib import Path

from app.errors import UsageError
from core.contracts import HARD_FORCE_LIMIT_N, NOISE_SIGMA_FACTOR, SENSORS, Plan, PlanError
from core.textfile import InputFileError
from fem.scene import BUILTIN, Scene, SceneError, load, tip_taken_as_rigid
from robot.truth import TruthError, conditions_of

MAX_WAYPOINTS = 2000        # one raster (plan, run, predict): beyond this the planning NLP and fem cost explode
MAX_TOTAL_PROBES = 10000    # a run's probe budget


def load_plan_option(path: str, option: str = "--plan") -> Plan:
    """The plan a command's ``option`` names; a plan that cannot be read or is malformed is one line naming the option
    and the file (``--plan p.json: plan version None is not supported ...``)."""
    try:
        return Plan.load(path)
    except PlanError as e:
        msg = str(e)
        for said, instead in ((f"cannot read plan {path}: ", "cannot read it: "), (f"plan {path}: ", "")):
            if msg.startswith(said):            # (Plan.load's own naming of the file: said once)
                msg = instead + msg[len(said):]
        raise UsageError(f"{option} {path}: {msg}") from None


def check_same_extent(truth, prior, where_prior: str, truth_name: str) -> None:
    """A simulated truth that is not the belief's kind of tissue (a 2D section against a 3D block) or not as wide
    (or, a block, as long) is refused: the localizer fits the tissue's stiffness, thickness and surface placement,
    not its extent, so a healthy truth of another width reads as a stone near the side (a 60 mm section under a
    40 mm prior: LR 2510, exit 0), and a 3D plan on a 2D truth felt the section's force at every y."""
    if truth.is_3d != prior.is_3d:
        kind = lambda sc: "a 3D block" if sc.is_3d else "a 2D section"     # noqa: E731
        raise UsageError(f"{where_prior} is {kind(prior)} but the simulated truth (scene {truth_name}) is "
                         f"{kind(truth)}: give a truth of the same kind")
    for key in ("width_m", "length_m"):
        a, b = getattr(prior.tissue, key), getattr(truth.tissue, key)
        if (a is None) != (b is None) or (a is not None and not math.isclose(a, b, rel_tol=1e-9)):
            raise UsageError(f"{where_prior}: tissue.{key} = {a!r} m but the simulated truth's (scene {truth_name}) "
                             f"is {b!r} m; the localizer fits the tissue's stiffness, thickness and surface, not its "
                             f"extent: give a belief of the same {key}")
    # the tip is the instrument in the arm's hand, known exactly: a belief with another one plans its depths and
    # reads its forces for a tip that is not there (a session-49 review: a 3 mm truth tip under a 5 mm belief ran,
    # pressed 4 mm with the 3 mm tip, and said STONE)
    for key in ("shape", "radius_m", "thickness_m"):
        a, b = getattr(prior.indenter, key), getattr(truth.indenter, key)
        same = a == b if isinstance(a, str) or a is None or b is None else math.isclose(a, b, rel_tol=1e-9)
        if not same:
            said = (lambda v: repr(v)) if key == "shape" else (lambda v: f"{v:g} m")
            raise UsageError(f"{where_prior}: indenter.{key} = {said(a)} but the simulated truth's (scene "
                             f"{truth_name}) is {said(b)}; the tip is the instrument, the same in the belief and the "
                             f"world: give the truth's [indenter] to the belief")
    if tip_taken_as_rigid(prior) != tip_taken_as_rigid(truth):     # its modulus only where fem does not neglect it
        said = lambda sc: ("rigid" if tip_taken_as_rigid(sc) else    # noqa: E731
                           f"elastic (indenter.youngs_pa = {sc.indenter.youngs_pa:g} Pa)")
        raise UsageError(f"{where_prior}: the tip is {said(prior)} but the simulated truth's (scene {truth_name}) is "
                         f"{said(truth)}; the tip is the instrument, the same in the belief and the world: give the "
                         f"truth's [indenter] to the belief")


def _parse(s: str, kind=float):
    try:
        v = kind(s)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"invalid {kind.__name__} value: {s!r}") from None
    return v


def finite_float(s: str) -> float:
    v = _parse(s)
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {s!r}")
    return v


# below this an indentation means nothing to a continuum model (an atom is about 1e-10 m across); far below it the
# stresses underflow (1e-300 m reported a von Mises peak of 0 Pa at x = 0)
MIN_DEPTH_M = 1e-12


def check_depth_floor(depth_m: float | None, option: str = "--depth-m") -> None:
    """UsageError for a positive indentation below MIN_DEPTH_M (0 and negative ones are each command's own)."""
    if depth_m is not None and 0 < depth_m < MIN_DEPTH_M:
        raise UsageError(f"{option} {depth_m:g}: below {MIN_DEPTH_M:g} m, where a continuum model means nothing (an "
                         f"atom is about 1e-10 m across); allowed: {MIN_DEPTH_M:g} m or deeper")


def positive_float(s: str) -> float:
    v = _parse(s)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {s!r}")
    return v


def nonnegative_float(s: str) -> float:
    v = _parse(s)
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {s!r}")
    return v


def float_range(lo: float, hi: float, *, lo_open: bool = True, hi_open: bool = False, unit: str = ""):
    """A finite float in (lo, hi] (the brackets as given)."""
    rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}{' ' + unit if unit else ''}"

    def parse(s: str) -> float:
        v = _parse(s)
        ok = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
        if not ok:
            raise argparse.ArgumentTypeError(f"must be a finite number in {rng}, got {s!r}")
        return v
    parse.__name__ = "float"
    return parse


def int_range(lo: int, hi: int | None = None):
    """An integer in [lo, hi]."""
    def parse(s: str) -> int:
        v = _parse(s, int)
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"must be an integer in [{lo}, {hi}], got {s!r}" if hi is not None
                                             else f"must be an integer >= {lo}, got {s!r}")
        return v
    parse.__name__ = "int"
    return parse


def host_name(s: str) -> str:
    """A controller's host name or IPv4 address: not empty (an unset shell variable), no spaces, no port or URL
    (ur_rtde connects to its own ports), a dotted quad of 0-255 when all digits, else letters, digits and hyphens
    in dot-separated labels (RFC 1123)."""
    if not s.strip() or any(c.isspace() for c in s):
        raise argparse.ArgumentTypeError(f"must be a host name or IP address, got {s!r}")
    try:
        ipaddress.IPv6Address(s.split("%")[0])
        raise argparse.ArgumentTypeError(f"{s!r} is an IPv6 address: a UR controller takes an IPv4 address (or a "
                                         f"host name)")
    except ipaddress.AddressValueError:
        pass
    if "/" in s or ":" in s:
        raise argparse.ArgumentTypeError(f"must be the controller's IP address or host name alone (no port or URL: "
                                         f"ur_rtde uses the UR's own ports), got {s!r}")
    labels = s.rstrip(".").split(".")
    if all(lab.isdigit() or lab.lower().startswith("0x") for lab in labels):
        # numbers only: the canonical dotted quad (the resolver reads 010 as octal 8 and 0x7f as hex: another host)
        try:
            ipaddress.IPv4Address(s.rstrip("."))
        except ipaddress.AddressValueError:
            raise argparse.ArgumentTypeError(f"must be an IPv4 address (four numbers 0-255, no leading zeros) or a "
                                             f"host name, got {s!r}") from None
    elif len(s) > 253 or not all(lab and len(lab) <= 63 and lab[0] != "-" and lab[-1] != "-"
                                 and all(c.isalnum() and c.isascii() or c in "-_" for c in lab) for lab in labels):
        raise argparse.ArgumentTypeError(f"must be an IPv4 address or a host name (letters, digits and hyphens "
                                         f"between dots), got {s!r}")
    return s


def grid_counts(s: str) -> tuple[int, int]:
    """``NXxNY``: waypoints along x and y of an area raster, each >= 1, at most MAX_WAYPOINTS in all."""
    parts = s.lower().split("x")
    try:
        nx, ny = (int(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be NXxNY (two integers, e.g. 10x10), got {s!r}") from None
    if nx < 1 or ny < 1 or nx * ny > MAX_WAYPOINTS:
        raise argparse.ArgumentTypeError(f"must be NXxNY with both counts >= 1 and NX*NY <= {MAX_WAYPOINTS}, "
                                         f"got {s!r}")
    return nx, ny


def float_list(n: int | None = None, what: str = "numbers"):
    """Comma-separated finite floats (exactly ``n`` when given)."""
    def parse(s: str) -> list[float]:
        try:
            v = [float(t) for t in s.split(",")]
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}, comma-separated, got {s!r}") from None
        if not all(math.isfinite(x) for x in v) or (n is not None and len(v) != n):
            raise argparse.ArgumentTypeError(f"must be {what}: {n or 'some'} finite numbers, comma-separated, "
                                             f"got {s!r}")
        return v
    parse.__name__ = "list"
    return parse


def polygon_vertices(s: str) -> list[tuple[float, float]]:
    """``"x,y;x,y;..."``: at least 3 finite (x, y) vertices in m."""
    try:
        v = [tuple(float(t) for t in pair.split(",")) for pair in s.strip().strip(";").split(";")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be vertices \"x,y;x,y;...\" in m, got {s!r}") from None
    if len(v) < 3 or any(len(p) != 2 or not all(math.isfinite(c) for c in p) for p in v):
        raise argparse.ArgumentTypeError(f"must be at least 3 vertices \"x,y;x,y;x,y\" (finite, m), got {s!r}")
    return v


# ---------------------------------------------------------------------------------------------- output paths

def _writable_parent(path: Path, option: str, shown=None) -> None:
    """The nearest existing ancestor of ``path`` must be a writable directory (so the rest can be created)."""
    p, path = path.absolute(), shown if shown is not None else path
    for anc in [p, *p.parents]:
        if anc.exists():
            if not anc.is_dir():
                raise UsageError(f"{option} {path}: {anc} is a file, not a directory")
            if not os.access(anc, os.W_OK | os.X_OK) or str(anc).startswith(("/proc", "/sys")):
                raise UsageError(f"{option} {path}: cannot create or write under {anc} (not writable)")
            return
        try:
            anc.lstat()          # a dangling symlink or an unreadable parent
        except FileNotFoundError:
            continue
        except OSError as e:
            raise UsageError(f"{option} {path}: {e.strerror}") from None


def refuse_inputs(path: str | None, option: str, inputs: dict | None) -> None:
    """UsageError when the output ``path`` is one of the command's ``inputs`` ({what: path}: the scene file, the
    plan, the prior) -- the same file, whatever the spelling or a link (session 56's review: ``--json`` on the scene
    or the plan replaced it, exit 0)."""
    if not path or path == "-" or not inputs:
        return
    for what, given in inputs.items():
        if not given or given == "-":
            continue
        try:
            same = os.path.samefile(path, given)
        except OSError:             # one of them is no file (a built-in scene's name, a path to be made)
            same = False
        if same:
            raise UsageError(f"{option} {path}: is {what} ({given}), which the command reads; writing there would "
                             f"replace it: choose another path")


def refuse_figures(plots: str | None, names, outputs: dict) -> None:
    """UsageError when an output file ({option: path}) is one of the figures (``names``) the command draws into the
    ``--plots`` directory: the figure would replace it, or it the figure (session 56's review: ``plan --out
    X/plan_joints.png --plots X`` left a PNG named as the plan, exit 0). Compared by resolved path, without needing
    either to exist."""
    if not plots:
        return
    figures = {(Path(plots) / n).resolve(): n for n in names}
    for option, path in outputs.items():
        if path and path != "-" and Path(path).resolve() in figures:
            raise UsageError(f"{option} {path}: is named as a figure that --plots {plots} draws "
                             f"({figures[Path(path).resolve()]}); give another path")


def check_output_file(path: str | None, option: str, replaced: bool = False, inputs: dict | None = None) -> None:
    """A file option (``--json``, ``--vtu``, ``--out plan.json``): not a directory, not a run's measured data (nor a
    symlink to it), its directory creatable/writable. ``replaced``: the file is written beside and renamed over the
    path, so an existing path must be a regular file (a device such as /dev/null would be replaced by one; a pipe
    can take a ``--json`` written in place). None (not given) and "-" (standard output) pass; an empty or blank path
    is refused (before session 45 it passed and was taken as not given: no file, and no word about it)."""
    if path is None or path == "-":
        return
    _not_blank(path, option, "a file path")
    refuse_measured(path, option)
    refuse_inputs(path, option, inputs)
    p = Path(path)
    try:
        os.stat(p)
    except OSError as e:
        if e.errno == errno.ELOOP:         # a symlink loop: nothing can be written through it
            raise UsageError(f"{option} {path}: {e.strerror}") from None
    if p.is_dir():
        raise UsageError(f"{option} {path}: is a directory; give a file path")
    if replaced and p.exists() and not p.is_file():
        raise UsageError(f"{option} {path}: is not a regular file (a device, pipe or socket), and the file is "
                         f"written beside it and renamed over it; give a file path")
    if p.exists():
        if not os.access(p, os.W_OK):
            raise UsageError(f"{option} {path}: file is not writable")
        return
    _writable_parent(p.parent, option, path)


def _not_blank(path: str, option: str, what: str) -> None:
    if not str(path).strip():
        raise UsageError(f"{option} {path!r}: an empty path; give {what}")


def check_output_dir(path: str | None, option: str) -> None:
    """A directory option (``--plots``, ``--out DIR``): not an existing file; creatable and writable; not empty or
    blank (``--out ''`` wrote a run into the current directory)."""
    if path is None:
        return
    _not_blank(path, option, "a directory")
    p = Path(path)
    if any(_in_raw(Path(q)) for q in (os.path.abspath(p), os.path.realpath(p))):     # (".." collapsed; links)
        raise UsageError(f"{option} {path}: inside a run's raw/ directory (its measured samples); choose another "
                         f"directory")
    if p.exists() and not p.is_dir():
        raise UsageError(f"{option} {path}: is a file, not a directory")
    _writable_parent(p, option)


MEASURED_NAMES = ("probes.jsonl", "raw", "run.json")


def _in_raw(p: Path) -> bool:
    """Is the absolute path ``p`` a run's raw/ directory or inside it?"""
    return any(a.name == "raw" and (a.parent / "probes.jsonl").exists() for a in (p, *p.parents))


def is_measured(path: str | Path) -> bool:
    """Is ``path`` a run's measured file (probes.jsonl, anything under raw/, a run.json next to a probes.jsonl) or a
    directory holding one?"""
    p = Path(os.path.abspath(path))       # ("RUN/raw/../other" is not under raw/)
    if p.is_dir() and ((p / "probes.jsonl").exists() or (p / "raw").is_dir()):
        return True
    if p.name == "probes.jsonl" or p.suffix == ".jsonl" and p.exists():
        return True
    if p.name.startswith("probes.jsonl.") and p.exists():      # a torn record set aside by a resume (.torn)
        return True
    if _in_raw(p):              # raw/ itself too
        return True
    if p.name == "run.json" and (p.parent / "probes.jsonl").exists():
        return True
    # what a run resumes from (its options, its rounds' plans) and reports: another command must not replace them
    run_dir = (p.parent / "probes.jsonl").exists() or (p.parent / "run_options.json").exists()
    return run_dir and (p.name in RUN_OWN_NAMES or p.name.startswith(("plan_round", "fig_run")))


RUN_OWN_NAMES = ("run_options.json", "result.json", "cell_world.json")


def refuse_measured(path: str | None, option: str) -> None:
    """UsageError when ``path``, or what it links to, is a run's measured data or a file the run resumes from."""
    if path and path != "-" and (is_measured(path) or is_measured(os.path.realpath(path))):   # realpath: no raise
        raise UsageError(f"{option} {path}: would overwrite a run's data (probes.jsonl and what a resume set aside of "
                         f"it, raw/, run.json, run_options.json, plan_round*.json, result.json, cell_world.json, its "
                         f"figure); choose another path")


def check_simulated_sensor(name: str, force_limit_n: float) -> None:
    """UsageError unless the simulated sensor preset ``name`` lets the driver enforce ``force_limit_n``: the driver
    refuses to probe when NOISE_SIGMA_FACTOR times its measured filtered free-air noise reaches half the limit
    (robot.driver). Judged here on the preset's white noise with no credit for the filter (drift and the short
    sample raise the measured filtered noise to 0.3-0.65 of the white noise on ur5e-builtin), so a simulated run that
    passes this check is not refused by the driver for its sensor."""
    spec = SENSORS[name]
    need = 2 * NOISE_SIGMA_FACTOR * spec.noise_std_n
    if need >= force_limit_n:
        ok = [n for n, s in SENSORS.items() if 2 * NOISE_SIGMA_FACTOR * s.noise_std_n < force_limit_n]
        raise UsageError(f"--sensor {name}: its noise ({spec.noise_std_n:g} N per axis) is too large for the force "
                         f"limit {force_limit_n:g} N: the driver needs {NOISE_SIGMA_FACTOR:g} noise sigmas below half "
                         f"the limit (it would stop before probing); allowed: {', '.join(ok)}"
                         + (f", or a plan whose force limit exceeds {need:g} N" if need < HARD_FORCE_LIMIT_N else ""))


def load_scene(spec: str, option: str = "scene") -> Scene:
    """fem.scene.load, with an unreadable file (binary, latin-1, a directory) named in a one-line error; a scene
    file's ``[truth]`` table (the simulated world's conditions, robot.truth) is checked too, whichever command reads
    the file, so a mistyped condition is refused before it could be relied on."""
    try:
        scene = load(spec)
        if spec not in BUILTIN:
            conditions_of(spec).check_scene(scene)
        return scene
    except TruthError as e:
        raise UsageError(f"{option} {spec}: {e}") from None
    except UnicodeDecodeError as e:
        raise UsageError(f"{option} {spec}: not a UTF-8 text (TOML) file ({e.reason} at byte {e.start})") from None
    except IsADirectoryError:
        raise UsageError(f"{option} {spec}: is a directory; give a scene TOML file or a built-in name") from None
    except InputFileError as e:
        raise UsageError(f"{option} {spec}: {e.reason}") from None
    except OSError as e:
        raise UsageError(f"{option} {spec}: cannot read: {e.strerror or e}") from None
    except SceneError as e:
        msg = str(e)
        # the option (or the scene argument's file) named, unless the message does already ("a 2D scene ..." does
        # not name the file: 'scene' in it was taken for that)
        named = option in msg if option.startswith("-") else str(spec) in msg
        raise SceneError(msg if named else f"{option} {spec}: {msg}") from None


def analysis_changes(args, sc) -> dict:
    """The scene's analysis fields a command's options override (``--order``, ``--mesh-size-m``,
    ``--surface-refine``, ``--plane``), checked against the scene as options (``--plane`` on a 3D block was reported
    as the scene's own field)."""
    if args.plane is not None and sc.is_3d:
        raise UsageError(f"--plane {args.plane}: {sc.name!r} is a 3D block, which has no plane assumption (plane "
                         f"strain or stress is for 2D sections); drop --plane")
    return {k: v for k, v in (("order", args.order), ("mesh_size_m", args.mesh_size_m),
                              ("surface_refine", args.surface_refine), ("plane", args.plane)) if v is not None}
