#!/usr/bin/env python3
"""Bad-input survey (issue 13): run the CLIs on ~200 kinds of bad input and classify what each one does.

    python bench/bad_input_survey.py --out bench-out/survey [--fresh] [--jobs 2] [--only ID_PREFIX ...] [--list]
        [--cli-palpate "python3 -m app.cli"] [--cli-cell "python3 -m app.cell"] [--keep]

Every case is run as a subprocess of the CLI (never imported), in a temp dir of its own under OUT/work/, with
stdin closed, a 6 GB address-space limit (so memory exhaustion shows as a MemoryError, not an OOM-killed machine)
and its own process group (killed with SIGKILL at the case's timeout). Outputs: OUT/survey.json (one object per
case: id, kind, description, argv, exit code, last stderr line, outcome, ...) and OUT/survey.md (table + counts).
The survey is resumable: case ids already in OUT/survey.json are skipped unless --fresh. It deletes nothing but
its own temp dirs (OUT/work/<id>-*/, removed after each case unless --keep).

CLI invocation (module paths will move): ``CLI`` below maps "palpate" / "palpate-cell" to an argv prefix. Default:
``python3 -m app.cli`` / ``python3 -m app.cell`` with PYTHONPATH = this checkout (so the checkout's code is
what runs, never a console script from PATH that may point elsewhere). Override with --cli-palpate / --cli-cell
(split with shlex) or the environment variables PALPATE_SURVEY_CLI_PALPATE / PALPATE_SURVEY_CLI_CELL (also read by
tests/test_bad_input.py), e.g. ``--cli-palpate "python3 -m app.cli" --cli-cell "python3 -m app.cell"`` or
``--cli-palpate palpate --cli-cell palpate-cell``.

Outcomes (classification rule, in this order):
  hang              the case exceeded its timeout (process group killed).
  traceback         "Traceback (most recent call last)" in stdout or stderr, whatever the exit code.
  nonfinite-output  exit 0 and a non-finite number in an output: any file the case created or modified (JSON and
                    JSONL parsed: NaN, Infinity or |x| > 1e300; .txt/.md/.csv/.toml/.vtu/.log scanned for the words
                    nan/inf/infinity) or standard output (same word scan).
  silent-accept     exit 0, nothing non-finite, but the case declares expect="refuse".
  accepted          exit 0, nothing non-finite, expect="ok-or-refuse".
  clear-error       exit 2 and the message is one line: the last non-empty stderr line is the message; every
                    earlier non-empty stderr line must be a progress line (starting with the program name,
                    "palpate" or "palpate-cell") or part of argparse's usage block (a line starting with "usage:"
                    and the indented lines that continue it). The "names" column says whether the message contains
                    the field/option the case is about (the case's ``mentions``).
  unclear-error     exit 2 but no message, or other lines (warnings, tables, several messages) besides it.
  other-exit        any other exit code (1, 3, 130, a signal ...).
  data-safety cases (kind data-safety; two CLI runs on one output directory): data-lost if a record (a line of a
  *.jsonl file) or, for a refused re-run, any file of the first run was deleted or changed (records moved aside
  into another *.jsonl under the directory still count as kept); pressed-twice if an index that had a finished
  record ("ok"/"force_limit") before the second run got another record; else safe. data-lost wins over
  pressed-twice (the message lists both).
"""
from __future__ import annotations

import argparse
import copy
import hashlib
import json
import math
import os
import re
import resource
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
CLI = {
    "palpate": shlex.split(os.environ.get("PALPATE_SURVEY_CLI_PALPATE", "")) or [sys.executable, "-m", "app.cli"],
    "palpate-cell": shlex.split(os.environ.get("PALPATE_SURVEY_CLI_CELL", "")) or [sys.executable, "-m", "app.cell"],
}
MEM_LIMIT_BYTES = 6 * 1024 ** 3
DIR = "<<mkdir>>"       # files: make a directory here
MISSING = "<<missing>>"  # scene/plan mutation: delete the key
OUTCOMES = ["clear-error", "unclear-error", "traceback", "hang", "silent-accept", "nonfinite-output", "accepted",
            "other-exit", "data-lost", "pressed-twice", "safe", "setup-failed"]


@dataclass
class Case:
    id: str
    kind: str                      # scene / option / plan / output-path / data-safety
    desc: str
    argv: list                     # ["palpate" | "palpate-cell", args...]; "{d}" -> case dir, "{plan}" etc. -> shared
    files: dict = field(default_factory=dict)   # relpath -> str | bytes | DIR | callable(shared_dict) -> str|bytes
    timeout: float = 20.0
    expect: str = "refuse"         # "refuse" or "ok-or-refuse"
    mentions: tuple = ()           # a clear message names one of these (field / option)
    fast: bool = False             # candidate for a quick subset (FAST_SUBSET below is what the test runs)
    special: str | None = None     # data-safety handler
    first: list | None = None      # data-safety: the first run's argv
    first_timeout: float = 90.0


# --------------------------------------------------------------------------------------------------- scene text

BASE = {
    "tissue": {"width_m": "0.07", "height_m": "0.05", "youngs_pa": "2500.0", "poisson": "0.4"},
    "indenter": {"shape": '"cylinder"', "radius_m": "0.005", "youngs_pa": "6.0e7", "poisson": "0.3",
                 "thickness_m": "0.02"},
    "analysis": {"plane": '"strain"', "order": "2", "mesh_size_m": "0.008", "surface_refine": "4.0",
                 "top_displacement_m": "0.005", "formulation": '"displacement"'},
}
BASE_STONE = {"x_m": "0.035", "depth_m": "0.025", "diameter_m": "0.015", "youngs_pa": "5.0e9", "poisson": "0.3"}
# every scene field: (section, key); "stone" means the first [[stone]]
FIELDS = [(s, k) for s in ("tissue",) for k in BASE["tissue"]] + [("stone", k) for k in BASE_STONE] + \
         [(s, k) for s in ("indenter", "analysis") for k in BASE[s]]


def scene_toml(changes: dict | None = None, stones: list | None = None, name: str = "survey",
               drop_sections: tuple = (), extra: str = "") -> str:
    """The base scene (paper-like, 8 mm mesh) as TOML with ``changes`` {"section.key": TOML literal | MISSING}."""
    secs = copy.deepcopy(BASE)
    st = copy.deepcopy(stones if stones is not None else [BASE_STONE])
    for k, v in (changes or {}).items():
        sec, key = k.split(".", 1)
        target = st[0] if sec == "stone" else secs[sec]
        if v == MISSING:
            target.pop(key, None)
        else:
            target[key] = v
    lines = [f'name = "{name}"']
    for sec in ("tissue", "indenter", "analysis"):
        if sec in drop_sections:
            continue
        lines.append(f"\n[{sec}]")
        lines += [f"{k} = {v}" for k, v in secs[sec].items()]
    for s in st:
        lines.append("\n[[stone]]")
        lines += [f"{k} = {v}" for k, v in s.items()]
    return "\n".join(lines) + "\n" + extra


def stone(x="0.035", depth="0.025", diameter="0.015"):
    return {"x_m": x, "depth_m": depth, "diameter_m": diameter, "youngs_pa": "5.0e9", "poisson": "0.3"}


# --------------------------------------------------------------------------------------------------- plan edits

def _edit(fn: Callable[[dict], object], raw: bool = False):
    """A files entry: the shared 5-probe plan (paper), edited by ``fn`` (returns the new object or None)."""
    def make(shared: dict):
        d = copy.deepcopy(shared["plan"])
        r = fn(d)
        d = d if r is None else r
        return d if raw else json.dumps(d, indent=1)
    return make


def _deepen(depth_m: float):
    """Every probe ``depth_m`` deep with pose, joints and depth limit consistent (tool axis = base -z here)."""
    def fn(d):
        try:
            sys.path.insert(0, str(REPO))
            from robot import ur5e
        except ImportError:
            ur5e = None
        tcp = d["frames"]["tcp_offset"]
        for p in d["probes"]:
            dz = depth_m - p["depth_m"]
            p["depth_m"] = depth_m
            p["indent_pose"][2] -= dz
            if ur5e is not None:
                q = ur5e.ik(p["indent_pose"], p["q_indent_rad"], tcp)
                if q is not None:
                    p["q_indent_rad"] = [float(v) for v in q]
        d["limits"]["depth_limit_m"] = depth_m + 0.001
    return fn


def _set(path: str, value):
    def fn(d):
        keys = path.split(".")
        t = d
        for k in keys[:-1]:
            t = t[int(k)] if isinstance(t, list) else t[k]
        last = keys[-1]
        if isinstance(t, list):
            t[int(last)] = value
        elif isinstance(value, str) and value == MISSING:
            del t[last]
        else:
            t[last] = value
    return fn


def _all_probes(key: str, value):
    def fn(d):
        for p in d["probes"]:
            p[key] = value
    return fn


def _text(fn: Callable[[str], str | bytes]):
    def make(shared):
        return fn(shared["plan_text"])
    return make


# --------------------------------------------------------------------------------------------------- the table

def cases() -> list[Case]:
    C: list[Case] = []

    def add(*a, **k):
        C.append(Case(*a, **k))

    SIM = ["palpate", "simulate", "{d}/scene.toml", "--load", "uniform", "--json", "{d}/out.json"]
    IND = ["palpate", "simulate", "{d}/scene.toml", "--load", "indent", "--x0-m", "0.035", "--depth-m", "0.003",
           "--json", "{d}/out.json"]

    # ---------------------------------------------------------------- scene files: the file itself
    add("scene-empty", "scene", "empty scene file (defaults silently used)", SIM, {"scene.toml": ""},
        mentions=("tissue", "empty"), fast=True)
    add("scene-comment-only", "scene", "scene file with only a comment", SIM, {"scene.toml": "# nothing\n"},
        mentions=("tissue", "empty"))
    add("scene-no-tissue", "scene", "scene without [tissue] (analysis only)", SIM,
        {"scene.toml": scene_toml(drop_sections=("tissue",))}, mentions=("tissue",), fast=True)
    add("scene-binary", "scene", "binary bytes in a .toml scene", SIM, {"scene.toml": bytes(range(256)) * 4},
        mentions=("scene", "toml", "utf"), fast=True)
    add("scene-binary-nosuffix", "scene", "binary file without .toml suffix as scene",
        ["palpate", "simulate", "{d}/scene.bin", "--json", "{d}/out.json"], {"scene.bin": b"\x89PNG\r\n\x1a\n\0\0\xff"},
        mentions=("scene",))
    add("scene-latin1", "scene", "latin-1 encoded scene (name with a-umlaut)", SIM,
        {"scene.toml": scene_toml(name="Gew\u00e4be").encode("latin-1")}, mentions=("scene", "utf", "encod"),
        fast=True)
    add("scene-bom", "scene", "UTF-8 scene with a byte-order mark", SIM,
        {"scene.toml": b"\xef\xbb\xbf" + scene_toml().encode()}, expect="ok-or-refuse", mentions=("scene", "toml"))
    add("scene-dir", "scene", "a directory named scene.toml given as scene", SIM, {"scene.toml": DIR},
        mentions=("scene", "directory"), fast=True)
    add("scene-dir-nosuffix", "scene", "a directory (no suffix) given as scene",
        ["palpate", "simulate", "{d}/sdir", "--json", "{d}/out.json"], {"sdir": DIR}, mentions=("scene", "directory"))
    add("scene-missing", "scene", "missing .toml scene file", SIM, {}, mentions=("scene", "exist"), fast=True)
    add("scene-unknown-name", "scene", "unknown built-in scene name",
        ["palpate", "simulate", "nosuch", "--json", "{d}/out.json"], mentions=("scene", "nosuch"), fast=True)
    add("scene-bad-toml", "scene", "invalid TOML syntax", SIM, {"scene.toml": "[tissue\nwidth_m = \n"},
        mentions=("toml",), fast=True)
    add("scene-unknown-top", "scene", "unknown top-level key", SIM, {"scene.toml": scene_toml(extra="colour = 1\n")},
        mentions=("colour",))
    add("scene-tissue-array", "scene", "[[tissue]] (array of tables) instead of [tissue]", SIM,
        {"scene.toml": scene_toml(drop_sections=("tissue",)) + "\n[[tissue]]\nwidth_m = 0.07\n"},
        mentions=("tissue",))
    add("scene-stone-scalar", "scene", "stone = 5 (not a table)",
        SIM, {"scene.toml": 'stone = 5\n' + scene_toml(stones=[])}, mentions=("stone",))
    add("scene-name-int", "scene", "name = 5", SIM, {"scene.toml": scene_toml().replace('name = "survey"', "name = 5")},
        mentions=("name",))
    add("scene-stone-missing-diam", "scene", "[[stone]] without diameter_m", SIM,
        {"scene.toml": scene_toml({"stone.diameter_m": MISSING})}, mentions=("diameter_m",), fast=True)
    add("scene-stone-empty", "scene", "empty [[stone]] table", SIM,
        {"scene.toml": scene_toml(stones=[{}])}, mentions=("x_m", "stone"))

    # ---------------------------------------------------------------- scene files: moduli, Poisson
    for key, vals in [("tissue.youngs_pa", ["nan", "inf", "-inf", "0.0", "-2500.0", "1e300", "1e-300", '"soft"',
                                            "[2500.0]", "1e400", "true"]),
                      ("stone.youngs_pa", ["nan", "inf", "1e300", "1e-300", "0.0", '"hard"']),
                      ("indenter.youngs_pa", ["nan", "-1.0", "1e300", "1e-300"])]:
        for v in vals:
            slug = v.strip('"[]').replace(".", "p").replace("-", "m").replace("+", "")
            cmd = IND if key.startswith("indenter") else SIM
            exp = "ok-or-refuse" if (key == "stone.youngs_pa" and v in ("1e300",)) else "refuse"
            add(f"scene-{key.replace('.', '-')}-{slug}", "scene", f"{key} = {v}", cmd,
                {"scene.toml": scene_toml({key: v})}, expect=exp, mentions=(key.split(".")[1],),
                fast=v in ("nan", "1e300", '"soft"') and key == "tissue.youngs_pa")
    for key, vals in [("tissue.poisson", ["0.5", "-1.0", "nan", "1.5", '"x"', "0.4999999"]),
                      ("stone.poisson", ["0.5", "nan"]), ("indenter.poisson", ["0.5"])]:
        for v in vals:
            slug = v.strip('"').replace(".", "p").replace("-", "m")
            cmd = IND if key.startswith("indenter") else SIM
            add(f"scene-{key.replace('.', '-')}-{slug}", "scene", f"{key} = {v}", cmd,
                {"scene.toml": scene_toml({key: v})}, expect="ok-or-refuse" if v == "0.4999999" else "refuse",
                mentions=("poisson",), fast=(key == "tissue.poisson" and v in ("0.5", "nan")))

    # ---------------------------------------------------------------- scene files: geometry
    geo = [
        ("stone-outside-side", "stone centre beyond the right edge (x_m 0.08)", {"stone.x_m": "0.08"}, SIM, "x_m"),
        ("stone-outside-top", "stone pokes out through the top (depth 5 mm, d 15 mm)", {"stone.depth_m": "0.005"},
         SIM, "depth_m"),
        ("stone-outside-bottom", "stone pokes out through the bottom", {"stone.depth_m": "0.048"}, SIM, "depth_m"),
        ("stone-touch-surface", "stone top exactly at the surface (depth = radius)", {"stone.depth_m": "0.0075"},
         SIM, "depth_m"),
        ("stone-0p2mm-indent", "stone top 0.2 mm under the surface, indented 4 mm above it (rigid stone)",
         {"stone.depth_m": "0.0077"}, IND[:-4] + ["--depth-m", "0.004", "--json", "{d}/out.json"], "depth_m"),
        ("thin-tissue-indent", "5 mm thick tissue indented 4 mm (inverted elements)",
         {"tissue.height_m": "0.005", "analysis.mesh_size_m": "0.002", "analysis.top_displacement_m": "0.001"},
         ["palpate", "simulate", "{d}/scene.toml", "--load", "indent", "--x0-m", "0.02", "--depth-m", "0.004",
          "--json", "{d}/out.json"], "height_m"),
        ("thin-tissue-default-disp", "2 mm thick tissue, top_displacement_m left at its 5 mm default",
         {"tissue.height_m": "0.002", "analysis.mesh_size_m": "0.001", "analysis.top_displacement_m": MISSING},
         SIM, "top_displacement_m"),
        ("disp-98pct", "top_displacement_m = 49 mm on a 50 mm tissue (98 % strain)",
         {"analysis.top_displacement_m": "0.049"}, SIM, "top_displacement_m"),
        ("disp-negative", "top_displacement_m = -1 mm", {"analysis.top_displacement_m": "-0.001"}, SIM,
         "top_displacement_m"),
        ("disp-nan", "top_displacement_m = nan", {"analysis.top_displacement_m": "nan"}, SIM, "top_displacement_m"),
        ("width-1000", "width_m = 1000 (huge mesh)", {"tissue.width_m": "1000.0"}, SIM, "width_m"),
        ("width-1e300", "width_m = 1e300", {"tissue.width_m": "1e300"}, SIM, "width_m"),
        ("height-1e-300", "height_m = 1e-300", {"tissue.height_m": "1e-300"}, SIM, "height_m"),
        ("width-zero", "width_m = 0", {"tissue.width_m": "0.0"}, SIM, "width_m"),
        ("width-string", 'width_m = "0.07" (a string)', {"tissue.width_m": '"0.07"'}, SIM, "width_m"),
        ("width-list", "width_m = [0.07] (a list)", {"tissue.width_m": "[0.07]"}, SIM, "width_m"),
        ("width-table", "width_m = {v = 0.07} (a table)", {"tissue.width_m": "{v = 0.07}"}, SIM, "width_m"),
        ("mesh-1e-7", "mesh_size_m = 1e-7", {"analysis.mesh_size_m": "1e-7"}, SIM, "mesh_size_m"),
        ("mesh-1e-5", "mesh_size_m = 1e-5", {"analysis.mesh_size_m": "1e-5"}, SIM, "mesh_size_m"),
        ("mesh-zero", "mesh_size_m = 0", {"analysis.mesh_size_m": "0.0"}, SIM, "mesh_size_m"),
        ("mesh-nan", "mesh_size_m = nan", {"analysis.mesh_size_m": "nan"}, SIM, "mesh_size_m"),
        ("mesh-string", 'mesh_size_m = "2mm"', {"analysis.mesh_size_m": '"2mm"'}, SIM, "mesh_size_m"),
        ("refine-1e6", "surface_refine = 1e6", {"analysis.surface_refine": "1e6"}, SIM, "surface_refine"),
        ("refine-1e3", "surface_refine = 1e3", {"analysis.surface_refine": "1e3"}, SIM, "surface_refine"),
        ("refine-zero", "surface_refine = 0", {"analysis.surface_refine": "0.0"}, SIM, "surface_refine"),
        ("refine-1e-300", "surface_refine = 1e-300 (top coarser than the tissue)",
         {"analysis.surface_refine": "1e-300"}, SIM, "surface_refine"),
        ("order-3", "order = 3", {"analysis.order": "3"}, SIM, "order"),
        ("order-float", "order = 2.0 (float)", {"analysis.order": "2.0"}, SIM, "order"),
        ("order-string", 'order = "2"', {"analysis.order": '"2"'}, SIM, "order"),
        ("order-bool", "order = true", {"analysis.order": "true"}, SIM, "order"),
        ("plane-axi", 'plane = "axisymmetric"', {"analysis.plane": '"axisymmetric"'}, SIM, "plane"),
        ("plane-int", "plane = 5", {"analysis.plane": "5"}, SIM, "plane"),
        ("formulation-mixed-p1", 'formulation = "mixed" with order = 1',
         {"analysis.formulation": '"mixed"', "analysis.order": "1"}, SIM, "formulation"),
        ("formulation-foo", 'formulation = "foo"', {"analysis.formulation": '"foo"'}, SIM, "formulation"),
        ("indenter-sphere", 'indenter shape = "sphere"', {"indenter.shape": '"sphere"'}, IND, "shape"),
        ("indenter-shape-int", "indenter shape = 5", {"indenter.shape": "5"}, IND, "shape"),
        ("indenter-radius-zero", "indenter radius_m = 0", {"indenter.radius_m": "0.0"}, IND, "radius_m"),
        ("indenter-radius-neg", "indenter radius_m = -0.005", {"indenter.radius_m": "-0.005"}, IND, "radius_m"),
        ("indenter-radius-nan", "indenter radius_m = nan", {"indenter.radius_m": "nan"}, IND, "radius_m"),
        ("indenter-radius-1e300", "indenter radius_m = 1e300", {"indenter.radius_m": "1e300"}, IND, "radius_m"),
        ("indenter-radius-1e-300", "indenter radius_m = 1e-300 (a needle)", {"indenter.radius_m": "1e-300"}, IND,
         "radius_m"),
        ("indenter-radius-0p1", "indenter radius_m = 0.1 (wider than the tissue)", {"indenter.radius_m": "0.1"},
         IND, "radius_m"),
        ("indenter-thick-nan", "indenter thickness_m = nan", {"indenter.thickness_m": "nan"}, IND, "thickness_m"),
        ("indenter-thick-1e300", "indenter thickness_m = 1e300", {"indenter.thickness_m": "1e300"}, IND,
         "thickness_m"),
        ("flat-elastic", 'flat punch with an elastic tip', {"indenter.shape": '"flat"'}, IND, "shape"),
        ("unknown-tissue-key", "unknown key tissue.colour", {"tissue.colour": '"red"'}, SIM, "colour"),
        ("unknown-stone-radius", "stone.radius_m instead of diameter_m",
         {"stone.radius_m": "0.0075", "stone.diameter_m": MISSING}, SIM, "radius_m"),
        ("unknown-indenter-key", "indenter.radius (typo)", {"indenter.radius": "0.005"}, IND, "radius"),
        ("unknown-analysis-key", "analysis.mesh_size (typo)", {"analysis.mesh_size": "0.004"}, SIM, "mesh_size"),
    ]
    fast_geo = {"stone-outside-side", "stone-0p2mm-indent", "disp-98pct", "width-string", "width-list", "mesh-nan",
                "order-3", "indenter-sphere", "indenter-radius-nan", "unknown-tissue-key", "thin-tissue-indent"}
    for cid, desc, ch, cmd, men in geo:
        exp = "ok-or-refuse" if cid in ("refine-1e3", "indenter-thick-1e300", "flat-elastic") else "refuse"
        add(f"scene-{cid}", "scene", desc, cmd, {"scene.toml": scene_toml(ch)}, expect=exp, mentions=(men,),
            fast=cid in fast_geo)
    add("scene-stones-overlap", "scene", "two overlapping stones", SIM,
        {"scene.toml": scene_toml(stones=[stone("0.030"), stone("0.040")])}, mentions=("stone",))
    add("scene-stones-touch", "scene", "two stones exactly touching", SIM,
        {"scene.toml": scene_toml(stones=[stone("0.025", diameter="0.010"), stone("0.035", diameter="0.010")])},
        mentions=("stone",))
    add("scene-stones-gap-1um", "scene", "two stones 1 micrometre apart (mesh cannot resolve the gap)", SIM,
        {"scene.toml": scene_toml(stones=[stone("0.025", diameter="0.010"), stone("0.035001", diameter="0.010")])},
        expect="ok-or-refuse", mentions=("stone",))
    # scene problems seen through other subcommands
    add("scene-plan-width-1000", "scene", "plan on a 1000 m wide tissue",
        ["palpate", "plan", "{d}/scene.toml", "--out", "{d}/plan.json"],
        {"scene.toml": scene_toml({"tissue.width_m": "1000.0"})}, mentions=("width_m",))
    add("scene-plan-binary", "scene", "plan with a binary scene file",
        ["palpate", "plan", "{d}/scene.toml", "--out", "{d}/plan.json"], {"scene.toml": b"\0\xff\xfe" * 100},
        mentions=("scene",), fast=True)
    add("scene-predict-latin1", "scene", "predict with a latin-1 scene",
        ["palpate", "predict", "{d}/scene.toml", "--waypoints", "5", "--json", "{d}/out.json"],
        {"scene.toml": scene_toml(name="Gew\u00e4be").encode("latin-1")}, mentions=("scene",))
    add("scene-predict-compare-binary", "scene", "predict --compare with a binary scene",
        ["palpate", "predict", "paper", "--waypoints", "5", "--mesh-size-m", "0.008", "--compare", "{d}/c.toml",
         "--json", "{d}/out.json"], {"c.toml": b"\0\xff" * 50}, mentions=("compare", "scene"))
    add("scene-run-dir", "scene", "run with a directory as scene",
        ["palpate", "run", "{d}/sdir", "--sim", "--out", "{d}/R"], {"sdir": DIR}, mentions=("scene",))

    # ---------------------------------------------------------------- options: simulate
    S = ["palpate", "simulate", "paper", "--mesh-size-m", "0.008", "--json", "{d}/out.json"]
    SI = S + ["--load", "indent", "--x0-m", "0.035", "--depth-m", "0.003"]
    opt = [
        ("sim-mesh-nan", S + ["--mesh-size-m", "nan"], "--mesh-size-m nan", "mesh", True),
        ("sim-mesh-zero", S + ["--mesh-size-m", "0"], "--mesh-size-m 0", "mesh", False),
        ("sim-mesh-neg", S + ["--mesh-size-m", "-0.002"], "--mesh-size-m -0.002", "mesh", True),
        ("sim-mesh-inf", S + ["--mesh-size-m", "inf"], "--mesh-size-m inf", "mesh", False),
        ("sim-mesh-1e-7", S + ["--mesh-size-m", "1e-7"], "--mesh-size-m 1e-7 (hang?)", "mesh", False),
        ("sim-mesh-abc", S + ["--mesh-size-m", "abc"], "--mesh-size-m abc (wrong type)", "mesh", True),
        ("sim-refine-1e6", S + ["--surface-refine", "1e6"], "--surface-refine 1e6", "refine", False),
        ("sim-refine-nan", S + ["--surface-refine", "nan"], "--surface-refine nan", "refine", False),
        ("sim-order-3", S + ["--order", "3"], "--order 3 (not a choice)", "order", True),
        ("sim-load-foo", S + ["--load", "foo"], "--load foo", "load", False),
        ("sim-indent-no-x0", S + ["--load", "indent", "--depth-m", "0.003"], "--load indent without --x0-m", "x0",
         True),
        ("sim-x0-nan", SI + ["--x0-m", "nan"], "--x0-m nan", "x0", True),
        ("sim-x0-neg", SI + ["--x0-m", "-0.01"], "--x0-m -0.01 (left of the tissue)", "x0", False),
        ("sim-x0-outside", SI + ["--x0-m", "1.0"], "--x0-m 1.0 (beyond the width)", "x0", True),
        ("sim-x0-inf", SI + ["--x0-m", "inf"], "--x0-m inf", "x0", False),
        ("sim-depth-nan", SI + ["--depth-m", "nan"], "indent --depth-m nan", "depth", True),
        ("sim-depth-neg", SI + ["--depth-m", "-0.004"], "indent --depth-m -0.004", "depth", False),
        ("sim-depth-zero", SI + ["--depth-m", "0"], "indent --depth-m 0", "depth", False),
        ("sim-depth-6mm", SI + ["--depth-m", "0.006"], "indent 6 mm with a 5 mm tip radius", "depth", True),
        ("sim-depth-49mm", SI + ["--depth-m", "0.049"], "indent 49 mm into 50 mm tissue", "depth", False),
        ("sim-radius-zero", SI + ["--indenter-radius-m", "0"], "--indenter-radius-m 0", "radius", True),
        ("sim-radius-nan", SI + ["--indenter-radius-m", "nan"], "--indenter-radius-m nan", "radius", False),
        ("sim-radius-1e300", SI + ["--indenter-radius-m", "1e300"], "--indenter-radius-m 1e300", "radius", False),
        ("sim-compare-nosuch", S + ["--compare", "nosuch", "--plots", "{d}/plots"],
         "--compare with an unknown scene", "nosuch", False),
        ("sim-no-scene", ["palpate", "simulate"], "simulate without SCENE", "scene", True),
    ]
    for cid, argv, desc, men, fast in opt:
        add(f"opt-{cid}", "option", desc, argv, mentions=(men,), fast=fast,
            expect="ok-or-refuse" if cid in ("sim-depth-zero",) else "refuse")

    # ---------------------------------------------------------------- options: predict
    P = ["palpate", "predict", "paper", "--waypoints", "5", "--mesh-size-m", "0.008", "--json", "{d}/out.json"]
    opt = [
        ("pred-wp-0", ["--waypoints", "0"], "--waypoints 0", "waypoints", True),
        ("pred-wp-neg", ["--waypoints", "-5"], "--waypoints -5", "waypoints", True),
        ("pred-wp-1", ["--waypoints", "1"], "--waypoints 1", "waypoints", False),
        ("pred-wp-1e7", ["--waypoints", "10000000"], "--waypoints 10000000 (hang)", "waypoints", False),
        ("pred-wp-1e9", ["--waypoints", "1000000000"], "--waypoints 1e9 (memory)", "waypoints", False),
        ("pred-wp-float", ["--waypoints", "1e7"], "--waypoints 1e7 (not an int)", "waypoints", True),
        ("pred-depth-nan", ["--depth-m", "nan"], "--depth-m nan", "depth", True),
        ("pred-depth-inf", ["--depth-m", "inf"], "--depth-m inf", "depth", False),
        ("pred-depth-neg", ["--depth-m", "-0.004"], "--depth-m -0.004", "depth", False),
        ("pred-depth-zero", ["--depth-m", "0"], "--depth-m 0", "depth", False),
        ("pred-depth-6mm", ["--depth-m", "0.006"], "--depth-m 0.006 deeper than the 5 mm tip radius", "depth", True),
        ("pred-depth-60mm", ["--depth-m", "0.06"], "--depth-m 0.06 deeper than the tissue", "depth", False),
        ("pred-margin-nan", ["--margin-m", "nan"], "--margin-m nan", "margin", True),
        ("pred-margin-neg", ["--margin-m", "-0.01"], "--margin-m -0.01", "margin", False),
        ("pred-margin-half", ["--margin-m", "0.035"], "--margin-m 0.035 (no room left)", "margin", False),
        ("pred-margin-big", ["--margin-m", "0.05"], "--margin-m 0.05 (margins cross)", "margin", False),
        ("pred-compare-nosuch", ["--compare", "nosuch"], "--compare nosuch", "nosuch", True),
        ("pred-radius-zero", ["--indenter-radius-m", "0"], "--indenter-radius-m 0", "radius", False),
        ("pred-radius-nan", ["--indenter-radius-m", "nan"], "--indenter-radius-m nan", "radius", False),
        ("pred-mesh-nan", ["--mesh-size-m", "nan"], "--mesh-size-m nan", "mesh", False),
        ("pred-refine-0", ["--surface-refine", "0"], "--surface-refine 0", "refine", False),
    ]
    for cid, extra, desc, men, fast in opt:
        add(f"opt-{cid}", "option", desc, P + extra, mentions=(men,), fast=fast,
            timeout=30 if "1e" in cid else 20)

    # ---------------------------------------------------------------- options: plan
    PL = ["palpate", "plan", "paper", "--out", "{d}/plan.json", "--waypoints", "5"]
    PLS = ["palpate", "plan", "paper", "--out", "{d}/plan.json"]
    opt = [
        ("plan-wp-0", PL + ["--waypoints", "0"], "--waypoints 0", "waypoints", True),
        ("plan-wp-neg", PL + ["--waypoints", "-3"], "--waypoints -3", "waypoints", False),
        ("plan-wp-1", PL + ["--waypoints", "1"], "--waypoints 1", "waypoints", False),
        ("plan-wp-1e5", PL + ["--waypoints", "100000"], "--waypoints 100000 (hang)", "waypoints", False),
        ("plan-wp-abc", PL + ["--waypoints", "abc"], "--waypoints abc", "waypoints", True),
        ("plan-spacing-0", PLS + ["--spacing-m", "0"], "--spacing-m 0", "spacing", True),
        ("plan-spacing-nan", PLS + ["--spacing-m", "nan"], "--spacing-m nan", "spacing", False),
        ("plan-spacing-neg", PLS + ["--spacing-m", "-0.002"], "--spacing-m -0.002", "spacing", False),
        ("plan-spacing-1e-9", PLS + ["--spacing-m", "1e-9"], "--spacing-m 1e-9 (6e7 waypoints)", "spacing", False),
        ("plan-spacing-1", PLS + ["--spacing-m", "1.0"], "--spacing-m 1.0 (wider than the tissue)", "spacing", False),
        ("plan-wp-and-spacing", PL + ["--spacing-m", "0.01"], "--waypoints with --spacing-m", "spacing", False),
        ("plan-margin-nan", PL + ["--margin-m", "nan"], "--margin-m nan", "margin", False),
        ("plan-margin-neg", PL + ["--margin-m", "-0.005"], "--margin-m -0.005 (outside the tissue)", "margin", False),
        ("plan-margin-big", PL + ["--margin-m", "0.04"], "--margin-m 0.04 (margins cross)", "margin", False),
        ("plan-xmin-gt-xmax", PL + ["--x-min-m", "0.05", "--x-max-m", "0.02"], "--x-min-m > --x-max-m", "x-m", True),
        ("plan-xmin-neg", PL + ["--x-min-m", "-0.01"], "--x-min-m -0.01", "x-min", False),
        ("plan-xmax-1", PL + ["--x-max-m", "1.0"], "--x-max-m 1.0 (beyond the width)", "x-max", False),
        ("plan-xmin-nan", PL + ["--x-min-m", "nan"], "--x-min-m nan", "x-min", False),
        ("plan-force-nan", PL + ["--force-limit-n", "nan"], "--force-limit-n nan", "force-limit", True),
        ("plan-force-inf", PL + ["--force-limit-n", "inf"], "--force-limit-n inf", "force-limit", False),
        ("plan-force-0", PL + ["--force-limit-n", "0"], "--force-limit-n 0", "force-limit", False),
        ("plan-force-neg", PL + ["--force-limit-n", "-2"], "--force-limit-n -2", "force-limit", False),
        ("plan-force-1e6", PL + ["--force-limit-n", "1e6"], "--force-limit-n 1e6 (above the 10 N hard cap)",
         "force-limit", True),
        ("plan-dlim-nan", PL + ["--depth-limit-m", "nan"], "--depth-limit-m nan", "depth-limit", True),
        ("plan-dlim-0", PL + ["--depth-limit-m", "0"], "--depth-limit-m 0", "depth-limit", False),
        ("plan-dlim-neg", PL + ["--depth-limit-m", "-0.004"], "--depth-limit-m -0.004", "depth-limit", False),
        ("plan-dlim-6mm", PL + ["--depth-limit-m", "0.006", "--depth-m", "0.006"],
         "--depth-m/--depth-limit-m 6 mm, deeper than the 5 mm tip radius", "depth", True),
        ("plan-dlim-0p1", PL + ["--depth-limit-m", "0.1"], "--depth-limit-m 0.1 (deeper than tissue)", "depth-limit",
         False),
        ("plan-ffrac-0", PL + ["--force-fraction", "0"], "--force-fraction 0", "force-fraction", False),
        ("plan-ffrac-nan", PL + ["--force-fraction", "nan"], "--force-fraction nan", "force-fraction", False),
        ("plan-ffrac-1p5", PL + ["--force-fraction", "1.5"], "--force-fraction 1.5 (above the limit)",
         "force-fraction", False),
        ("plan-ffrac-neg", PL + ["--force-fraction", "-0.5"], "--force-fraction -0.5", "force-fraction", False),
        ("plan-mindepth-nan", PL + ["--min-depth-m", "nan"], "--min-depth-m nan", "min-depth", False),
        ("plan-mindepth-neg", PL + ["--min-depth-m", "-1"], "--min-depth-m -1", "min-depth", False),
        ("plan-mindepth-gt-lim", PL + ["--min-depth-m", "0.01"], "--min-depth-m above --depth-limit-m", "min-depth",
         False),
        ("plan-depth-nan", PL + ["--depth-m", "nan"], "--depth-m nan", "depth", True),
        ("plan-depth-inf", PL + ["--depth-m", "inf"], "--depth-m inf", "depth", False),
        ("plan-depth-neg", PL + ["--depth-m", "-0.004"], "--depth-m -0.004", "depth", False),
        ("plan-depth-0", PL + ["--depth-m", "0"], "--depth-m 0", "depth", False),
        ("plan-depth-15mm", PL + ["--depth-m", "0.015"], "--depth-m 0.015 (default depth limit 4 mm)", "depth", False),
        ("plan-pose-nan", PL + ["--tissue-pose", "nan", "0", "0.05", "0", "0", "0"], "--tissue-pose with nan",
         "tissue-pose", True),
        ("plan-pose-far", PL + ["--tissue-pose", "5", "0", "0.05", "0", "0", "0"],
         "--tissue-pose 5 m away (out of reach)", "tissue-pose", False),
        ("plan-pose-5vals", PL + ["--tissue-pose", "0.4", "0", "0.05", "0", "0"], "--tissue-pose with 5 values",
         "tissue-pose", False),
        ("plan-pose-upside", PL + ["--tissue-pose", "0.4", "-0.035", "0.05", "3.14159", "0", "0"],
         "--tissue-pose upside down (surface facing the floor)", "tissue-pose", False),
        ("plan-tcp-nan", PL + ["--tcp-offset", "0", "0", "nan", "0", "0", "0"], "--tcp-offset with nan",
         "tcp-offset", False),
        ("plan-tcp-5m", PL + ["--tcp-offset", "0", "0", "5", "0", "0", "0"], "--tcp-offset 5 m long tool",
         "tcp-offset", False),
        ("plan-ah-0", PL + ["--approach-height-m", "0"], "--approach-height-m 0", "approach-height", False),
        ("plan-ah-neg", PL + ["--approach-height-m", "-0.01"], "--approach-height-m -0.01 (below the surface)",
         "approach-height", True),
        ("plan-ah-nan", PL + ["--approach-height-m", "nan"], "--approach-height-m nan", "approach-height", False),
        ("plan-as-0", PL + ["--approach-speed-m-s", "0"], "--approach-speed-m-s 0", "approach-speed", False),
        ("plan-as-nan", PL + ["--approach-speed-m-s", "nan"], "--approach-speed-m-s nan", "approach-speed", False),
        ("plan-as-100", PL + ["--approach-speed-m-s", "100"], "--approach-speed-m-s 100 (above the hard cap)",
         "approach-speed", False),
        ("plan-ps-0", PL + ["--probe-speed-m-s", "0"], "--probe-speed-m-s 0", "probe-speed", True),
        ("plan-ps-neg", PL + ["--probe-speed-m-s", "-0.002"], "--probe-speed-m-s -0.002", "probe-speed", False),
        ("plan-ps-nan", PL + ["--probe-speed-m-s", "nan"], "--probe-speed-m-s nan", "probe-speed", False),
        ("plan-ps-10", PL + ["--probe-speed-m-s", "10"], "--probe-speed-m-s 10 (above the hard cap)", "probe-speed",
         False),
        ("plan-dwell-neg", PL + ["--dwell-s", "-5"], "--dwell-s -5", "dwell", True),
        ("plan-dwell-nan", PL + ["--dwell-s", "nan"], "--dwell-s nan", "dwell", False),
        ("plan-dwell-1e9", PL + ["--dwell-s", "1e9"], "--dwell-s 1e9", "dwell", False),
        ("plan-tilt-neg", PL + ["--tilt-tol-deg", "-1"], "--tilt-tol-deg -1", "tilt", True),
        ("plan-tilt-nan", PL + ["--tilt-tol-deg", "nan"], "--tilt-tol-deg nan", "tilt", False),
        ("plan-tilt-180", PL + ["--tilt-tol-deg", "180"], "--tilt-tol-deg 180", "tilt", False),
        ("plan-branch-2", PL + ["--branch", "1,1"], "--branch 1,1 (two signs)", "branch", False),
        ("plan-branch-abc", PL + ["--branch", "a,b,c"], "--branch a,b,c", "branch", False),
        ("plan-no-out", ["palpate", "plan", "paper"], "plan without --out", "out", True),
    ]
    for cid, argv, desc, men, fast in opt:
        exp = "ok-or-refuse" if cid in ("plan-tilt-180", "plan-dwell-1e9", "plan-wp-1") else "refuse"
        add(f"opt-{cid}", "option", desc, argv, mentions=(men,), fast=fast, expect=exp,
            timeout=30 if cid in ("plan-wp-1e5", "plan-spacing-1e-9") else 20)

    # ---------------------------------------------------------------- options: run (fast: 5 waypoints, budget 10)
    R = ["palpate", "run", "paper", "--sim", "--out", "{d}/R", "--waypoints", "5", "--budget-probes", "10",
         "--no-figure"]
    opt = [
        ("run-wp-0", ["--waypoints", "0"], "--waypoints 0", "waypoints", True),
        ("run-wp-neg", ["--waypoints", "-5"], "--waypoints -5", "waypoints", True),
        ("run-wp-1", ["--waypoints", "1"], "--waypoints 1", "waypoints", False),
        ("run-wp-1e5", ["--waypoints", "100000"], "--waypoints 100000", "waypoints", False),
        ("run-rwp-0", ["--refine-waypoints", "0"], "--refine-waypoints 0", "refine-waypoints", False),
        ("run-rwp-neg", ["--refine-waypoints", "-1"], "--refine-waypoints -1", "refine-waypoints", False),
        ("run-budget-0", ["--budget-probes", "0"], "--budget-probes 0", "budget", False),
        ("run-budget-neg", ["--budget-probes", "-1"], "--budget-probes -1", "budget", False),
        ("run-budget-3", ["--budget-probes", "3"], "--budget-probes 3 (below the coarse raster's 5)", "budget", False),
        ("run-target-nan", ["--target-uncertainty-m", "nan"], "--target-uncertainty-m nan", "target", False),
        ("run-target-0", ["--target-uncertainty-m", "0"], "--target-uncertainty-m 0", "target", False),
        ("run-target-neg", ["--target-uncertainty-m", "-1"], "--target-uncertainty-m -1", "target", False),
        ("run-target-inf", ["--target-uncertainty-m", "inf"], "--target-uncertainty-m inf", "target", False),
        ("run-sensor-foo", ["--sensor", "foo"], "--sensor foo", "sensor", False),
        ("run-strategy-foo", ["--strategy", "foo"], "--strategy foo", "strategy", True),
        ("run-seed-abc", ["--seed", "abc"], "--seed abc", "seed", True),
        ("run-scene-nosuch", [], "run nosuch (unknown scene)", "nosuch", False),
    ]
    for cid, extra, desc, men, fast in opt:
        argv = R + extra if cid != "run-scene-nosuch" else [a if a != "paper" else "nosuch" for a in R]
        exp = "ok-or-refuse" if cid in ("run-budget-3", "run-target-inf", "run-wp-1") else "refuse"
        add(f"opt-{cid}", "option", desc, argv, mentions=(men,), fast=fast, timeout=45, expect=exp)
    add("opt-run-no-out", "option", "run without --out", ["palpate", "run", "paper", "--sim"], mentions=("out",),
        fast=True)
    add("opt-run-host-noconfirm", "option", "run --host with stdin closed (confirmation prompt hits EOF)",
        ["palpate", "run", "paper", "--host", "192.0.2.1", "--out", "{d}/R", "--waypoints", "5", "--no-figure"],
        mentions=("confirm", "yes"), timeout=45)
    add("opt-run-sim-and-host", "option", "run --sim and --host together",
        R + ["--host", "192.0.2.1"], mentions=("host", "sim"), fast=True)

    # ---------------------------------------------------------------- options: bench
    add("opt-bench-no-out", "option", "bench without --out", ["palpate", "bench"], mentions=("out",), fast=True)
    add("opt-bench-only-foo", "option", "bench --only foo", ["palpate", "bench", "--out", "{d}/B", "--only", "foo"],
        mentions=("only",), fast=True)
    add("opt-bench-dir-missing", "option", "bench --bench-dir that does not exist",
        ["palpate", "bench", "--out", "{d}/B", "--bench-dir", "{d}/nosuch"], mentions=("bench-dir", "bench"))
    add("opt-bench-dir-file", "option", "bench --bench-dir pointing at a file",
        ["palpate", "bench", "--out", "{d}/B", "--bench-dir", "{d}/f.txt"], {"f.txt": "x"},
        mentions=("bench-dir", "bench"))
    add("opt-bench-dir-empty", "option", "bench --bench-dir an empty directory",
        ["palpate", "bench", "--out", "{d}/B", "--bench-dir", "{d}/empty"], {"empty": DIR},
        mentions=("bench-dir", "bench"))

    # ---------------------------------------------------------------- options: palpate-cell
    CE = ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/R", "--sim-mesh-m", "0.008"]
    opt = [
        ("cell-payload-nan", ["--payload-kg", "nan"], "--payload-kg nan", "payload", True),
        ("cell-payload-neg", ["--payload-kg", "-1"], "--payload-kg -1", "payload", False),
        ("cell-payload-1e6", ["--payload-kg", "1e6"], "--payload-kg 1e6", "payload", False),
        ("cell-sensor-foo", ["--sensor", "foo"], "--sensor foo", "sensor", True),
        ("cell-simmesh-neg", ["--sim-mesh-m", "-0.002"], "--sim-mesh-m -0.002", "sim-mesh", True),
        ("cell-simmesh-nan", ["--sim-mesh-m", "nan"], "--sim-mesh-m nan", "sim-mesh", False),
        ("cell-simmesh-0", ["--sim-mesh-m", "0"], "--sim-mesh-m 0 (silently the default?)", "sim-mesh", False),
        ("cell-simmesh-1e-7", ["--sim-mesh-m", "1e-7"], "--sim-mesh-m 1e-7", "sim-mesh", False),
        ("cell-truth-nosuch", ["--truth", "nosuch"], "--truth nosuch", "truth", True),
        ("cell-truth-missing", ["--truth", "{d}/missing.toml"], "--truth missing.toml", "truth", True),
        ("cell-inject-bad", ["--inject", "explode:1"], "--inject explode:1", "inject", True),
        ("cell-inject-nan", ["--inject", "stall:nan"], "--inject stall:nan", "inject", False),
        ("cell-seed-abc", ["--seed", "abc"], "--seed abc", "seed", False),
        ("cell-force-model-foo", ["--force-model", "foo"], "--force-model foo", "force-model", False),
    ]
    for cid, extra, desc, men, fast in opt:
        add(f"opt-{cid}", "option", desc, CE + extra, mentions=(men,), fast=fast, timeout=30)
    add("opt-cell-truth-binary", "option", "--truth a binary .toml", CE + ["--truth", "{d}/t.toml"],
        {"t.toml": b"\0\xff" * 64}, mentions=("truth", "scene"), timeout=30)
    add("opt-cell-no-plan", "option", "palpate-cell without --plan", ["palpate-cell", "--sim", "--out", "{d}/R"],
        mentions=("plan",), fast=True)
    add("opt-cell-no-source", "option", "palpate-cell without --sim/--host",
        ["palpate-cell", "--plan", "{plan}", "--out", "{d}/R"], mentions=("sim", "host"), fast=True)
    add("opt-cell-inject-host", "option", "--inject with --host",
        ["palpate-cell", "--host", "192.0.2.1", "--plan", "{plan}", "--out", "{d}/R", "--inject", "stall:1"],
        mentions=("inject",), fast=True)
    add("opt-cell-host-sensor", "option", "palpate-cell --host with --sensor (a simulation option; did nothing)",
        ["palpate-cell", "--host", "192.0.2.1", "--plan", "{plan}", "--out", "{d}/R", "--yes", "--sensor", "ideal"],
        mentions=("sensor",), fast=True)
    add("opt-cell-inject-never", "option", "--inject disconnect-after-probes=99 on a plan of fewer probes",
        CE + ["--inject", "disconnect-after-probes=99"], mentions=("inject",), timeout=30)
    add("opt-run-host-seed", "option", "palpate run --host with --seed (a simulation option; did nothing)",
        ["palpate", "run", "paper", "--host", "192.0.2.1", "--seed", "3", "--out", "{d}/R"], mentions=("seed",),
        fast=True)
    add("opt-ft-duration-tiny", "option", "palpate ft --duration-s 1e-6 (reported 0 Hz)",
        ["palpate", "ft", "--ft", "netft", "--duration-s", "1e-6"], mentions=("duration",), fast=True)
    add("opt-cell-host-noconfirm", "option", "palpate-cell --host with stdin closed (prompt hits EOF)",
        ["palpate-cell", "--host", "192.0.2.1", "--plan", "{plan}", "--out", "{d}/R"], mentions=("confirm", "yes"))

    # ---------------------------------------------------------------- output paths
    outp = [
        ("sim-json-dir", S + ["--json", "{d}/dir"], {"dir": DIR}, "simulate --json an existing directory", "json"),
        ("sim-json-proc", S + ["--json", "/proc/x/y"], {}, "simulate --json /proc/x/y (unwritable)", "json"),
        ("sim-json-under-file", S + ["--json", "{d}/f.txt/out.json"], {"f.txt": "x"},
         "simulate --json below an existing file", "json"),
        ("sim-plots-file", S + ["--plots", "{d}/f.txt"], {"f.txt": "x"}, "simulate --plots an existing file", "plots"),
        ("sim-plots-proc", S + ["--plots", "/proc/x/y"], {}, "simulate --plots /proc/x/y", "plots"),
        ("sim-vtu-dir", S + ["--vtu", "{d}/dir"], {"dir": DIR}, "simulate --vtu an existing directory", "vtu"),
        ("sim-vtu-proc", S + ["--vtu", "/proc/x/y.vtu"], {}, "simulate --vtu /proc/x/y.vtu", "vtu"),
        ("pred-json-dir", P + ["--json", "{d}/dir"], {"dir": DIR}, "predict --json an existing directory", "json"),
        ("pred-json-proc", P + ["--json", "/proc/x/y"], {}, "predict --json /proc/x/y", "json"),
        ("pred-plots-file", P + ["--plots", "{d}/f.txt"], {"f.txt": "x"}, "predict --plots an existing file", "plots"),
        ("plan-out-dir", PL + ["--out", "{d}/dir"], {"dir": DIR}, "plan --out an existing directory", "out"),
        ("plan-out-proc", PL + ["--out", "/proc/x/y"], {}, "plan --out /proc/x/y", "out"),
        ("plan-out-under-file", PL + ["--out", "{d}/f.txt/plan.json"], {"f.txt": "x"},
         "plan --out below an existing file", "out"),
        ("plan-plots-file", PL + ["--plots", "{d}/f.txt"], {"f.txt": "x"}, "plan --plots an existing file", "plots"),
        ("plan-plots-proc", PL + ["--plots", "/proc/x/y"], {}, "plan --plots /proc/x/y", "plots"),
        ("plan-json-dir", PL + ["--json", "{d}/dir"], {"dir": DIR}, "plan --json an existing directory", "json"),
        ("plan-out-figure", ["palpate", "plan", "paper", "--waypoints", "5", "--out", "{d}/P/plan_joints.png",
                             "--plots", "{d}/P"], {}, "plan --out a figure that --plots draws", "out"),
        ("plan-json-proc", PL + ["--json", "/proc/x/y"], {}, "plan --json /proc/x/y", "json"),
        ("run-out-file", R + ["--out", "{d}/f.txt"], {"f.txt": "x"}, "run --out an existing file", "out"),
        ("run-out-proc", R + ["--out", "/proc/x/y"], {}, "run --out /proc/x/y", "out"),
        ("run-json-dir", R + ["--json", "{d}/dir"], {"dir": DIR}, "run --json an existing directory", "json"),
        ("run-json-proc", R + ["--json", "/proc/x/y"], {}, "run --json /proc/x/y", "json"),
        ("bench-out-file", ["palpate", "bench", "--out", "{d}/f.txt", "--only", "planner", "--quick"],
         {"f.txt": "x"}, "bench --out an existing file", "out"),
        ("bench-out-proc", ["palpate", "bench", "--out", "/proc/x/y", "--only", "planner", "--quick"], {},
         "bench --out /proc/x/y", "out"),
        ("bench-json-proc", ["palpate", "bench", "--out", "{d}/B", "--json", "/proc/x/y", "--bench-dir", "{d}/e"],
         {"e": DIR}, "bench --json /proc/x/y (with an empty --bench-dir)", "json"),
        ("cell-out-file", ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/f.txt", "--sim-mesh-m", "0.008"],
         {"f.txt": "x"}, "palpate-cell --out an existing file", "out"),
        ("cell-out-proc", ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "/proc/x/y", "--sim-mesh-m", "0.008"],
         {}, "palpate-cell --out /proc/x/y", "out"),
        ("cell-json-dir", CE + ["--json", "{d}/dir"], {"dir": DIR}, "palpate-cell --json an existing directory",
         "json"),
        ("cell-json-proc", CE + ["--json", "/proc/x/y"], {}, "palpate-cell --json /proc/x/y", "json"),
    ]
    fast_out = {"sim-json-dir", "sim-json-proc", "sim-plots-file", "plan-out-dir", "plan-out-proc", "pred-json-proc",
                "bench-out-proc"}
    for cid, argv, files, desc, men in outp:
        slow = cid.startswith(("run-", "cell-", "bench-out"))
        add(f"out-{cid}", "output-path", desc, argv, files, mentions=(men,), fast=cid in fast_out,
            timeout=45 if slow else 20)

    # ---------------------------------------------------------------- plan files (palpate-cell; some via run)
    def cell(name="p.json"):
        return ["palpate-cell", "--sim", "--plan", "{d}/" + name, "--out", "{d}/R", "--sim-mesh-m", "0.008"]

    def runp(name="p.json"):
        return R + ["--plan", "{d}/" + name]

    nan = float("nan")
    plans = [
        ("truncated", _text(lambda t: t[: len(t) // 2]), "plan file cut in half", "plan", True, cell()),
        ("binary", b"\x89PNG\0\xff\xfe" * 40, "binary plan file", "plan", True, cell()),
        ("latin1", _text(lambda t: t.replace('"paper-prior"', '"Gew\u00e4be-prior"').encode("latin-1")),
         "latin-1 encoded plan", "plan", False, cell()),
        ("empty", "", "empty plan file", "plan", True, cell()),
        ("dir", DIR, "a directory as --plan", "plan", True, cell()),
        ("missing", None, "missing plan file", "plan", True, cell()),
        ("array", "[1, 2, 3]", "plan is a JSON array", "plan", True, cell()),
        ("string", '"plan"', "plan is a JSON string", "plan", False, cell()),
        ("version-3", _edit(_set("version", 3)), "plan version 3 (newer than this palpate; 2 is current)", "version",
         True, cell()),
        ("version-missing", _edit(_set("version", MISSING)), "plan without version", "version", False, cell()),
        ("version-str", _edit(_set("version", "1")), 'plan version "1" (string)', "version", False, cell()),
        ("scene-string", _edit(_set("scene", "paper")), "plan whose scene is a string", "scene", True, cell()),
        ("scene-missing", _edit(_set("scene", MISSING)), "plan without scene", "scene", False, cell()),
        ("probes-dict", _edit(_set("probes", {"0": 1})), "probes is an object", "probes", False, cell()),
        ("probes-empty", _edit(_set("probes", [])), "plan with no probes", "probes", False, cell()),
        ("deep-6mm", _edit(_deepen(0.006)), "probes 6 mm deep, 5 mm tip radius (pose, depth, limit consistent)",
         "depth", True, cell()),
        ("deep-15mm", _edit(_deepen(0.015)), "probes 15 mm deep, 5 mm tip radius (pose, depth, limit consistent)",
         "depth", False, cell()),
        ("dwell-neg", _edit(_set("motion.dwell_s", -5.0)), "motion.dwell_s = -5", "dwell", True, cell()),
        ("dwell-str", _edit(_set("motion.dwell_s", "long")), 'motion.dwell_s = "long"', "dwell", False, cell()),
        ("pose-nan", _edit(_set("probes.0.indent_pose.0", nan)), "NaN in probes[0].indent_pose", "indent_pose",
         True, cell()),
        ("pose-inf", _edit(_set("probes.1.approach_pose.2", float("inf"))), "Infinity in probes[1].approach_pose",
         "approach_pose", False, cell()),
        ("pose-5", _edit(lambda d: d["probes"][0].__setitem__("indent_pose", d["probes"][0]["indent_pose"][:5])), "indent_pose with 5 entries",
         "indent_pose", False, cell()),
        ("pose-str", _edit(_set("probes.0.indent_pose.2", "0.05")), "a string in indent_pose", "indent_pose", False,
         cell()),
        ("q-nan", _edit(_set("probes.0.q_indent_rad.1", nan)), "NaN in q_indent_rad", "q_indent_rad", False, cell()),
        ("index-str", _edit(lambda d: d["probes"][2].__setitem__("index", "2")), 'probe index "2" (string)', "index",
         True, cell()),
        ("index-dup", _edit(lambda d: d["probes"][1].__setitem__("index", 0)), "two probes with index 0", "index",
         False, cell()),
        ("index-neg", _edit(lambda d: d["probes"][1].__setitem__("index", -1)), "probe index -1", "index", False,
         cell()),
        ("probe-speed-str", _edit(_set("motion.probe_speed_m_s", "fast")), 'probe_speed_m_s = "fast"', "probe_speed",
         True, cell()),
        ("probe-speed-0", _edit(_set("motion.probe_speed_m_s", 0.0)), "probe_speed_m_s = 0", "probe_speed", False,
         cell()),
        ("probe-speed-neg", _edit(_set("motion.probe_speed_m_s", -0.002)), "probe_speed_m_s = -0.002", "probe_speed",
         False, cell()),
        ("approach-speed-nan", _edit(_set("motion.approach_speed_m_s", nan)), "approach_speed_m_s = NaN",
         "approach_speed", False, cell()),
        ("approach-height-neg", _edit(_set("motion.approach_height_m", -0.01)), "approach_height_m = -0.01",
         "approach_height", False, cell()),
        ("contact-thr-neg", _edit(_set("motion.contact_threshold_n", -1.0)), "contact_threshold_n = -1",
         "contact_threshold", False, cell()),
        ("force-1e6", _edit(_set("limits.force_limit_n", 1e6)), "limits.force_limit_n = 1e6 (hard cap 10 N)",
         "force_limit", True, cell()),
        ("force-nan", _edit(_set("limits.force_limit_n", nan)), "limits.force_limit_n = NaN", "force_limit", False,
         cell()),
        ("force-str", _edit(_set("limits.force_limit_n", "2")), 'limits.force_limit_n = "2"', "force_limit", False,
         cell()),
        ("depth-limit-0p1", _edit(_set("limits.depth_limit_m", 0.1)), "limits.depth_limit_m = 0.1", "depth_limit",
         False, cell()),
        ("x-outside", _edit(_set("probes.0.x_m", 0.5)), "probes[0].x_m = 0.5 (pose left unchanged)", "x_m", False,
         cell()),
        ("workspace-inverted", _edit(lambda d: d["limits"].update(workspace_min_m=[0.8, 0.8, 0.8],
                                                                  workspace_max_m=[-0.8, -0.8, -0.1])),
         "workspace_min_m above workspace_max_m", "workspace", False, cell()),
        ("tissue-pose-far", _edit(_set("frames.tissue_pose_base.0", 5.0)), "tissue pose 5 m away", "tissue_pose",
         False, cell()),
        ("unknown-probe-key", _edit(lambda d: d["probes"][0].__setitem__("colour", "red")), "unknown key in a probe",
         "colour", False, cell()),
        ("notes-list", _edit(_set("notes", [1, 2])), "notes is a list", "notes", False, cell()),
        ("toml-scene-no-truth", _edit(lambda d: d["scene"].__setitem__("name", "mytissue-prior")),
         "plan of a TOML scene (name mytissue) and no --truth", "truth", True, cell()),
        ("prior-E-1e9", _edit(lambda d: d["scene"]["tissue"].__setitem__("youngs_pa", 1e9)),
         "plan whose prior E is 1e9 (run --plan)", "youngs_pa", False, runp()),
        ("run-truncated", _text(lambda t: t[: len(t) // 3]), "run --plan truncated", "plan", True, runp()),
        ("run-binary", b"\0\xff" * 100, "run --plan binary", "plan", False, runp()),
        ("run-stones", _edit(lambda d: d["scene"].__setitem__("stone", [{"x_m": 0.035, "depth_m": 0.025,
                                                                            "diameter_m": 0.015}])),
         "run --plan whose scene has stones", "stone", False, runp()),
        ("run-scene-string", _edit(_set("scene", "paper")), "run --plan whose scene is a string", "scene", False,
         runp()),
        ("run-deep-6mm", _edit(_deepen(0.006)), "run --plan with probes 6 mm deep (5 mm tip)", "depth", False,
         runp()),
    ]
    for cid, content, desc, men, fast, argv in plans:
        files = {} if content is None else {"p.json": content}
        exp = "ok-or-refuse" if cid in ("latin1", "unknown-probe-key", "notes-list") else "refuse"
        slow = argv[1] == "run" or cid.startswith(("deep", "dwell", "force-1e6", "index", "probe-speed-str",
                                                   "toml", "x-outside"))
        add(f"plan-{cid}", "plan", desc, argv, files, mentions=(men,), fast=fast and not slow, expect=exp,
            timeout=90 if cid == "prior-E-1e9" else (45 if slow or argv[0] == "palpate-cell" else 20))

    # ---------------------------------------------------------------- data safety
    RUN = ["palpate", "run", "paper", "--sim", "--out", "{d}/R", "--waypoints", "5", "--budget-probes", "10",
           "--no-figure"]
    RUN15 = ["palpate", "run", "paper", "--sim", "--out", "{d}/R", "--no-figure"]
    CELL15 = ["palpate-cell", "--sim", "--plan", "{plan15}", "--out", "{d}/R", "--sim-mesh-m", "0.008"]
    ds = [
        ("run-then-bad-scene", "run paper, then run nosuch with the same --out: records kept?", RUN,
         ["palpate", "run", "nosuch", "--sim", "--out", "{d}/R"], "refused-rerun"),
        ("run-then-bad-option", "run paper, then the same --out with --budget-probes 0", RUN,
         RUN + ["--budget-probes", "0"], "refused-rerun"),
        ("run-then-bad-plan", "run paper, then the same --out with a truncated --plan", RUN,
         RUN + ["--plan", "{d}/bad.json"], "refused-rerun"),
        ("run-then-same", "run paper twice with the same --out (resume or refuse, never delete)", RUN, RUN,
         "rerun"),
        ("run-json-into-log", "run paper, then rerun with --json R/probes.jsonl", RUN,
         RUN + ["--json", "{d}/R/probes.jsonl"], "rerun"),
        ("run-kill9-resume", "run killed with SIGKILL after 4 records, restarted with the same --out", RUN15, RUN15,
         "kill"),
        ("cell-then-bad-plan", "palpate-cell run, then the same --out with a truncated plan",
         ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/R", "--sim-mesh-m", "0.008"],
         ["palpate-cell", "--sim", "--plan", "{d}/bad.json", "--out", "{d}/R", "--sim-mesh-m", "0.008"],
         "refused-rerun"),
        ("cell-json-into-log", "palpate-cell run, then rerun with --json R/probes.jsonl",
         ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/R", "--sim-mesh-m", "0.008"],
         ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/R", "--sim-mesh-m", "0.008", "--json",
          "{d}/R/probes.jsonl"], "rerun"),
        ("cell-kill9-resume", "palpate-cell killed with SIGKILL after 4 records, restarted", CELL15, CELL15, "kill"),
        ("cell-fresh", "palpate-cell run, then --fresh on the same --out (old records must survive somewhere)",
         ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/R", "--sim-mesh-m", "0.008"],
         ["palpate-cell", "--sim", "--plan", "{plan}", "--out", "{d}/R", "--sim-mesh-m", "0.008", "--fresh"],
         "fresh"),
        ("plan-overwrite-failed", "plan --out P, then a refused plan (--waypoints 0) to the same P",
         ["palpate", "plan", "paper", "--out", "{d}/R/plan.json", "--waypoints", "5"],
         ["palpate", "plan", "paper", "--out", "{d}/R/plan.json", "--waypoints", "0"], "refused-rerun"),
        ("simulate-json-failed", "simulate --json J, then a refused simulate to the same J",
         ["palpate", "simulate", "paper", "--mesh-size-m", "0.008", "--json", "{d}/R/out.json"],
         ["palpate", "simulate", "{d}/scene.toml", "--json", "{d}/R/out.json"], "refused-rerun"),
    ]
    for cid, desc, first, second, how in ds:
        files = {"bad.json": _text(lambda t: t[: len(t) // 2])}
        if cid == "simulate-json-failed":
            files = {"scene.toml": scene_toml({"tissue.youngs_pa": "-1.0"})}
        add(f"ds-{cid}", "data-safety", desc, second, files, special=how, first=first,
            expect="ok-or-refuse", timeout=150 if "kill" in cid or how in ("rerun", "fresh") else 60,
            first_timeout=150 if "kill" in cid else 90)
    return C


# tests/test_bad_input.py's subset: representative, each case well under 5 s on the current code
FAST_SUBSET = (
    # scene files
    "scene-empty", "scene-no-tissue", "scene-binary", "scene-latin1", "scene-dir", "scene-missing",
    "scene-stone-missing-diam", "scene-tissue-youngs_pa-nan", "scene-tissue-youngs_pa-1e300",
    "scene-tissue-youngs_pa-soft", "scene-tissue-poisson-0p5", "scene-tissue-poisson-nan", "scene-stone-outside-side",
    "scene-stone-0p2mm-indent", "scene-thin-tissue-indent", "scene-disp-98pct", "scene-width-string",
    "scene-width-list", "scene-order-3", "scene-indenter-sphere", "scene-unknown-tissue-key", "scene-plan-binary",
    # options
    "opt-sim-x0-outside", "opt-sim-depth-6mm", "opt-pred-wp-0", "opt-pred-depth-nan", "opt-plan-force-nan",
    "opt-plan-force-1e6", "opt-plan-dwell-neg", "opt-plan-tilt-neg", "opt-plan-depth-nan", "opt-plan-no-out",
    "opt-cell-truth-nosuch", "opt-bench-only-foo",
    # output paths
    "out-sim-json-dir", "out-sim-json-proc", "out-plan-out-dir", "out-plan-out-proc", "out-pred-json-proc",
    # plan files
    "plan-truncated", "plan-binary", "plan-array", "plan-version-3", "plan-scene-string", "plan-dir",
)


# --------------------------------------------------------------------------------------------------- running

def cli_prefix(name: str, cli: dict) -> list[str]:
    return list(cli[name])


def subst(argv: list, d: Path, shared: dict) -> list[str]:
    m = {"d": str(d), "plan": shared.get("plan_path", ""), "plan15": shared.get("plan15_path", "")}
    return [a.format(**m) if isinstance(a, str) else str(a) for a in argv]


def child_env(cache_dir: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("PALPATE_CACHE_DIR", str(cache_dir))
    env.update(MPLBACKEND="Agg", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONUNBUFFERED="1")
    env.pop("PYTHONWARNINGS", None)
    return env


def _limits():
    try:
        resource.setrlimit(resource.RLIMIT_AS, (MEM_LIMIT_BYTES, MEM_LIMIT_BYTES))
    except (ValueError, OSError):
        pass


def _kill(p: subprocess.Popen) -> None:
    try:
        os.killpg(p.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def execute(argv: list[str], cwd: Path, env: dict, timeout: float) -> dict:
    t0 = time.perf_counter()
    p = subprocess.Popen(argv, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, start_new_session=True, preexec_fn=_limits)
    try:
        out, err = p.communicate(timeout=timeout)
        hang = False
    except subprocess.TimeoutExpired:
        _kill(p)
        out, err = p.communicate()
        hang = True
    return {"rc": p.returncode, "stdout": out.decode("utf-8", "replace"), "stderr": err.decode("utf-8", "replace"),
            "hang": hang, "elapsed_s": round(time.perf_counter() - t0, 2)}


def write_files(d: Path, files: dict, shared: dict) -> None:
    for rel, content in files.items():
        p = d / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        if callable(content):
            content = content(shared)
        if isinstance(content, str) and content == DIR:
            p.mkdir(parents=True, exist_ok=True)
        elif isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content)


def snapshot(d: Path) -> dict:
    snap = {}
    for p in d.rglob("*"):
        if p.is_file():
            try:
                snap[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
            except OSError:
                pass
    return snap


_WORD = re.compile(r"(?<![A-Za-z_])(nan|[-+]?inf(inity)?)(?![A-Za-z_])", re.IGNORECASE)


def nonfinite_in_json(obj, path="$") -> str | None:
    if isinstance(obj, float):
        if not math.isfinite(obj) or abs(obj) > 1e300:
            return f"{path} = {obj!r}"
    elif isinstance(obj, dict):
        for k, v in obj.items():
            r = nonfinite_in_json(v, f"{path}.{k}")
            if r:
                return r
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            r = nonfinite_in_json(v, f"{path}[{i}]")
            if r:
                return r
    return None


def scan_file(p: Path, strip: str = "") -> str | None:
    """A description of the first non-finite number in ``p``, or None."""
    suf = p.suffix.lower()
    try:
        if suf == ".json":
            r = nonfinite_in_json(json.loads(p.read_text()))
            return f"{p.name}: {r}" if r else None
        if suf == ".jsonl":
            for i, line in enumerate(p.read_text().splitlines()):
                if line.strip():
                    try:
                        r = nonfinite_in_json(json.loads(line))
                    except json.JSONDecodeError:
                        continue
                    if r:
                        return f"{p.name} line {i + 1}: {r}"
            return None
        if suf in (".txt", ".md", ".csv", ".toml", ".vtu", ".log"):
            m = _WORD.search(p.read_text(errors="replace").replace(strip or "\0", "{d}"))
            return f"{p.name}: '{m.group(0)}'" if m else None
    except (OSError, ValueError) as e:
        return None if suf != ".json" else f"{p.name}: unreadable JSON ({type(e).__name__})"
    return None


def scan_outputs(d: Path, before: dict, stdout: str) -> str | None:
    for p in sorted(d.rglob("*")):
        if p.is_file() and (str(p) not in before or before[str(p)] != snapshot_one(p)):
            r = scan_file(p, str(d))
            if r:
                return r
    m = _WORD.search(stdout)
    return f"stdout: '{m.group(0)}' in {stdout[max(0, m.start() - 60): m.end() + 20]!r}" if m else None


def snapshot_one(p: Path) -> str:
    try:
        return hashlib.sha256(p.read_bytes()).hexdigest()
    except OSError:
        return ""


def message_lines(stderr: str) -> list[str]:
    return [ln.rstrip() for ln in stderr.splitlines() if ln.strip()]


def one_line_message(stderr: str) -> bool:
    """The rule of the docstring: the last non-empty stderr line is the message; earlier lines are progress lines
    (starting with the program name) or argparse's usage block."""
    lines = message_lines(stderr)
    if not lines:
        return False
    in_usage = False
    for ln in lines[:-1]:
        if ln.startswith("usage:"):
            in_usage = True
            continue
        if in_usage and ln[:1].isspace():
            continue
        in_usage = False
        if ln.startswith("palpate"):
            continue
        return False
    return True


def _norm(s: str) -> str:
    return s.lower().replace("-", "_")


def names_field(mentions, outcome: str, message: str) -> bool | None:
    """Does an error message name the case's field or option? ("--probe-speed-m-s" and "probe_speed_m_s" match.)"""
    if not mentions or outcome not in ("clear-error", "unclear-error"):
        return None
    return any(_norm(m) in _norm(message) for m in mentions)


def last_line(r: dict) -> str:
    lines = message_lines(r["stderr"]) or message_lines(r["stdout"])
    return lines[-1][:400] if lines else ""


def classify(r: dict, expect: str, nonfinite: str | None) -> str:
    if r["hang"]:
        return "hang"
    if "Traceback (most recent call last)" in r["stdout"] + r["stderr"]:
        return "traceback"
    if r["rc"] == 0:
        if nonfinite:
            return "nonfinite-output"
        return "silent-accept" if expect == "refuse" else "accepted"
    if r["rc"] == 2:
        return "clear-error" if one_line_message(r["stderr"]) else "unclear-error"
    return "other-exit"


def _jsonl_lines(d: Path) -> Counter:
    c = Counter()
    for p in d.rglob("*.jsonl"):
        try:
            c.update(ln for ln in p.read_text(errors="replace").splitlines() if ln.strip())
        except OSError:
            pass
    return c


def _log_lines(path: Path) -> list[str]:
    try:
        return [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return []


def _records(path: Path) -> list[dict]:
    out = []
    if path.is_file():
        for ln in path.read_text(errors="replace").splitlines():
            try:
                rec = json.loads(ln)
            except json.JSONDecodeError:
                continue
            if isinstance(rec, dict):
                out.append(rec)
    return out


def data_safety(case: Case, d: Path, env: dict, cli: dict, shared: dict) -> dict:
    first = cli_prefix(case.first[0], cli) + subst(case.first[1:], d, shared)
    second = cli_prefix(case.argv[0], cli) + subst(case.argv[1:], d, shared)
    R = d / "R"
    info = {"first_argv": first}
    if case.special == "kill":
        t0 = time.perf_counter()
        p = subprocess.Popen(first, cwd=d, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL, start_new_session=True, preexec_fn=_limits)
        n = 0
        while time.perf_counter() - t0 < case.first_timeout and p.poll() is None:
            n = len([r for r in _records(R / "probes.jsonl")])
            if n >= 4:
                break
            time.sleep(0.05)
        _kill(p)
        p.wait()
        info["first"] = f"killed with SIGKILL after {n} records ({time.perf_counter() - t0:.1f} s)"
        if n < 1:
            return {**info, "outcome": "setup-failed", "message": "the first run wrote no record before the timeout"}
    else:
        r1 = execute(first, d, env, case.first_timeout)
        info["first"] = f"exit {r1['rc']}{' (hang)' if r1['hang'] else ''}: {last_line(r1)}"
        if r1["hang"] or r1["rc"] not in (0,):
            return {**info, "outcome": "setup-failed", "message": f"first run failed: {info['first']}"}
    before_files = snapshot(R)
    before_lines = _jsonl_lines(R)
    before_recs = _records(R / "probes.jsonl")
    before_log = _log_lines(R / "probes.jsonl")
    finished = {rec.get("index") for rec in before_recs if rec.get("status") in ("ok", "force_limit", "depth_limit")}
    r2 = execute(second, d, env, case.timeout)
    after_files = snapshot(R)
    after_lines = _jsonl_lines(R)
    after_recs = _records(R / "probes.jsonl")
    lost = before_lines - after_lines
    problems = []
    if lost:
        problems.append(f"{sum(lost.values())} of {sum(before_lines.values())} records gone")
    refused = case.special == "refused-rerun" or r2["rc"] != 0
    if case.special == "refused-rerun" or (refused and case.special != "kill"):
        changed = sorted(Path(k).relative_to(d).as_posix() for k, v in before_files.items()
                         if after_files.get(k) != v)
        if changed:
            problems.append(f"refused re-run changed/deleted {len(changed)} file(s) of the first run: "
                            + ", ".join(changed[:4]) + (" ..." if len(changed) > 4 else ""))
    new_lines = Counter(_log_lines(R / "probes.jsonl")) - Counter(before_log)
    again = Counter()
    for ln in new_lines.elements():
        try:
            again[json.loads(ln).get("index")] += 1
        except (json.JSONDecodeError, AttributeError):
            pass
    twice = [] if case.special == "fresh" else sorted((i for i in finished if again.get(i)), key=str)
    if lost and twice:
        problems.append(f"indices pressed again: {twice[:12]}")
    elif twice:
        problems.append(f"finished indices pressed again: {twice[:12]}")
    orphans = 0
    if (R / "raw").is_dir():
        referenced = {rec.get("raw_file") for rec in after_recs}
        orphans = sum(1 for p in (R / "raw").glob("*.npz") if str(p.relative_to(R)) not in referenced)
    if orphans and problems:
        problems.append(f"{orphans} raw/*.npz file(s) no longer referenced")
    if any("gone" in p or "changed/deleted" in p for p in problems):
        outcome = "data-lost"
    elif twice:
        outcome = "pressed-twice"
    else:
        outcome = "safe"
    tb = "Traceback (most recent call last)" in r2["stdout"] + r2["stderr"]
    second_desc = f"second run exit {r2['rc']}{' (hang)' if r2['hang'] else ''}{' TRACEBACK' if tb else ''}: " \
                  f"{last_line(r2)}"
    return {**info, "outcome": outcome, "rc": r2["rc"], "hang": r2["hang"], "elapsed_s": r2["elapsed_s"],
            "last_stderr": last_line(r2), "traceback": tb,
            "message": "; ".join(problems + [second_desc]) if problems else second_desc,
            "records_before": len(before_recs), "records_after": len(after_recs)}


def prepare_shared(shared_dir: Path, cli: dict, cache_dir: Path) -> dict:
    """Plans every plan case edits (5 probes) and the kill-resume case uses (15 probes): made once with the CLI."""
    shared_dir.mkdir(parents=True, exist_ok=True)
    env = child_env(cache_dir)
    out = {}
    for key, n in (("plan", 5), ("plan15", 15)):
        path = shared_dir / f"{key}.json"
        if not path.is_file():
            r = execute(cli_prefix("palpate", cli) + ["plan", "paper", "--out", str(path), "--waypoints", str(n)],
                        shared_dir, env, 120)
            if r["rc"] != 0 or not path.is_file():
                raise RuntimeError(f"cannot make the shared plan {path}: {last_line(r)}")
        out[f"{key}_path"] = str(path)
    out["plan_text"] = Path(out["plan_path"]).read_text()
    out["plan"] = json.loads(out["plan_text"])
    return out


_TABLE: dict | None = None


def case_by_id(cid: str) -> Case:
    """Cases hold closures (not picklable): a worker process rebuilds the table and looks the case up."""
    global _TABLE
    if _TABLE is None:
        _TABLE = {c.id: c for c in cases()}
    return _TABLE[cid]


def run_case_id(cid: str, work: Path, cli: dict, shared: dict, cache_dir: Path, keep: bool = False) -> dict:
    return run_case(case_by_id(cid), work, cli, shared, cache_dir, keep)


def run_case(case: Case, work: Path, cli: dict, shared: dict, cache_dir: Path, keep: bool = False) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    d = Path(tempfile.mkdtemp(prefix="case-", dir=work))     # no case id in the path: ids contain "nan", "inf"
    env = child_env(cache_dir)
    res = {"id": case.id, "kind": case.kind, "description": case.desc, "expect": case.expect,
           "mentions": list(case.mentions)}
    try:
        try:
            write_files(d, case.files, shared)
        except Exception as e:  # noqa: BLE001
            return {**res, "argv": case.argv, "outcome": "setup-failed", "message": f"{type(e).__name__}: {e}"}
        argv = cli_prefix(case.argv[0], cli) + subst(case.argv[1:], d, shared)
        res["argv"] = [a.replace(str(d), "{d}") for a in argv]
        if case.special:
            r = data_safety(case, d, env, cli, shared)
            r["first_argv"] = [a.replace(str(d), "{d}") for a in r.get("first_argv", [])]
            return {**res, **{k: (v.replace(str(d), "{d}") if isinstance(v, str) else v) for k, v in r.items()}}
        before = snapshot(d)
        r = execute(argv, d, env, case.timeout)
        nonfinite = scan_outputs(d, before, r["stdout"].replace(str(d), "{d}")) if (r["rc"] == 0 and not r["hang"]) else None
        outcome = classify(r, case.expect, nonfinite)
        msg = last_line(r)
        if outcome == "nonfinite-output":
            msg = f"{nonfinite}"
        elif outcome in ("accepted", "silent-accept"):
            msg = (message_lines(r["stdout"]) or [""])[-1][:300]
        names = names_field(case.mentions, outcome, last_line(r))
        return {**res, "rc": r["rc"], "hang": r["hang"], "elapsed_s": r["elapsed_s"],
                "last_stderr": last_line(r).replace(str(d), "{d}"), "outcome": outcome,
                "message": msg.replace(str(d), "{d}"), "names_field": names, "nonfinite": nonfinite,
                "stderr_tail": "\n".join(message_lines(r["stderr"])[-6:]).replace(str(d), "{d}")[-1500:]}
    finally:
        if not keep:
            shutil.rmtree(d, ignore_errors=True)


# --------------------------------------------------------------------------------------------------- report

def write_report(out: Path, results: dict, table: list[Case], meta: dict) -> Counter:
    order = [c.id for c in table if c.id in results] + [k for k in results if k not in {c.id for c in table}]
    rows = [results[k] for k in order]
    by_id = {c.id: c for c in table}
    for r in rows:                 # recomputed, so a changed ``mentions`` needs no re-run
        if r["id"] in by_id and "last_stderr" in r and r.get("kind") != "data-safety":
            r["names_field"] = names_field(by_id[r["id"]].mentions, r["outcome"], r.get("last_stderr", ""))
    (out / "survey.json").write_text(json.dumps({"meta": meta, "cases": rows}, indent=1))
    counts = Counter(r["outcome"] for r in rows)
    lines = ["# Bad-input survey (issue 13)", "",
             f"{len(rows)} cases; CLI: `{' '.join(meta['cli']['palpate'])}` / `{' '.join(meta['cli']['palpate-cell'])}`"
             f"; generated by `bench/bad_input_survey.py` (classification rules in its docstring).", "",
             "| outcome | count |", "|---|---|"]
    lines += [f"| {k} | {counts[k]} |" for k in OUTCOMES if counts.get(k)]
    lines += ["", "| id | kind | description | outcome | names field | message |", "|---|---|---|---|---|---|"]

    def esc(s):
        return str(s).replace("|", "\\|").replace("\n", " ")
    for r in rows:
        nf = {True: "yes", False: "NO", None: ""}[r.get("names_field")]
        lines.append(f"| {r['id']} | {r['kind']} | {esc(r['description'])} | {r['outcome']} | {nf} | "
                     f"{esc(r.get('message', ''))[:240]} |")
    (out / "survey.md").write_text("\n".join(lines) + "\n")
    return counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--out", default="bench-out/survey", help="output directory (default bench-out/survey)")
    ap.add_argument("--fresh", action="store_true", help="run every case again (ignore survey.json); with --only, "
                                                         "just the selected ones")
    ap.add_argument("--jobs", type=int, default=2, help="cases in parallel (default 2)")
    ap.add_argument("--only", nargs="+", metavar="PREFIX", help="run only case ids starting with these")
    ap.add_argument("--redo", nargs="+", metavar="OUTCOME", default=[],
                    help="run again the cases whose recorded outcome is one of these (e.g. hang setup-failed)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--keep", action="store_true", help="keep each case's temp dir under OUT/work/")
    ap.add_argument("--cli-palpate", help="argv prefix for `palpate` (shlex-split), default: "
                                          + " ".join(CLI["palpate"]))
    ap.add_argument("--cli-cell", help="argv prefix for `palpate-cell` (shlex-split), default: "
                                       + " ".join(CLI["palpate-cell"]))
    a = ap.parse_args(argv)
    cli = dict(CLI)
    if a.cli_palpate:
        cli["palpate"] = shlex.split(a.cli_palpate)
    if a.cli_cell:
        cli["palpate-cell"] = shlex.split(a.cli_cell)
    table = cases()
    ids = [c.id for c in table]
    dup = [k for k, v in Counter(ids).items() if v > 1]
    assert not dup, f"duplicate case ids: {dup}"
    if a.list:
        for c in table:
            print(f"{c.id:40s} {c.kind:12s} {c.expect:13s} {'fast' if c.id in FAST_SUBSET else '    '} {c.desc}")
        print(f"{len(table)} cases ({len(FAST_SUBSET)} in tests/test_bad_input.py's subset)")
        return 0
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    results = {}
    if (out / "survey.json").is_file() and not (a.fresh and not a.only):
        results = {r["id"]: r for r in json.loads((out / "survey.json").read_text())["cases"]}
        if a.fresh:                # --fresh --only P: run the selected cases again, keep the others
            results = {k: v for k, v in results.items() if not k.startswith(tuple(a.only))}
    results = {k: v for k, v in results.items() if v.get("outcome") not in a.redo}
    todo = [c for c in table if c.id not in results and (not a.only or c.id.startswith(tuple(a.only)))]
    cache_dir = (out / "cache").resolve()
    work = (out / "work").resolve()
    t0 = time.perf_counter()
    shared = prepare_shared((out / "shared").resolve(), cli, cache_dir)
    meta = {"cli": cli, "repo": str(REPO), "jobs": a.jobs}
    print(f"{len(todo)} cases to run ({len(results)} already in {out / 'survey.json'}), {a.jobs} at a time",
          flush=True)
    with ProcessPoolExecutor(max_workers=a.jobs) as pool:
        futs = {pool.submit(run_case_id, c.id, work, cli, shared, cache_dir, a.keep): c for c in todo}
        for i, f in enumerate(as_completed(futs), 1):
            c = futs[f]
            try:
                r = f.result()
            except Exception as e:  # noqa: BLE001 - a harness bug in one case must not lose the others
                r = {"id": c.id, "kind": c.kind, "description": c.desc, "argv": c.argv, "outcome": "setup-failed",
                     "message": f"harness: {type(e).__name__}: {e}"}
            results[c.id] = r
            print(f"[{i}/{len(todo)}] {c.id}: {r['outcome']} ({r.get('elapsed_s', '-')} s) {r.get('message', '')[:120]}",
                  flush=True)
            meta["last_wall_s"] = round(time.perf_counter() - t0, 1)
            write_report(out, results, table, meta)
    meta["last_wall_s"] = round(time.perf_counter() - t0, 1)
    counts = write_report(out, results, table, meta)
    print(f"survey: {sum(counts.values())} cases in {out / 'survey.md'}; this invocation took "
          f"{meta['last_wall_s']:.0f} s")
    for k in OUTCOMES:
        if counts.get(k):
            print(f"  {k:18s} {counts[k]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
