"""Session 49: bad input and small defects left from session 48's reviews."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from app import cell
from app.cli import build_parser, main
from app.errors import UsageError
from app.runexec import check_resume, run_options
from fem import cachesize
from fem.scene import load

ROOT = Path(__file__).resolve().parents[1]
# the first argument of every call that names a cache entry's kind, the 3D table's calibrations, and KIND constants
_KIND_USE = re.compile(r"(?<!\w)(?:load_or_build|diskcache\.load|entry_path|memo|cached_fingerprint)\(\s*\"([a-z0-9]+)\"|"
                       r"^KIND = \"([a-z0-9]+)\"|f\"([a-z0-9]+)-\{key\}\.npz\"", re.M)


def test_the_cache_kinds_listed_are_exactly_those_the_code_writes():
    found = set()
    for f in (*ROOT.glob("fem/*.py"), *ROOT.glob("planner/*.py")):
        text = f.read_text()
        found |= {next(g for g in m.groups() if g) for m in _KIND_USE.finditer(text)}
        if "-cal-" in text:
            found |= {f"{k}-cal" for k in re.findall(r"def cache_path.*?f\"([a-z0-9]+)-\{key\}", text, re.S)}
    assert len(found) >= 15
    assert found == cachesize.KINDS


def test_cache_clear_refuses_a_kind_that_is_not_one(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PALPATE_CACHE_DIR", str(tmp_path))
    assert main(["cache", "clear", "--kind", "factor3"]) == 2
    err = capsys.readouterr().err
    assert "--kind 'factor3'" in err and "factor3d" in err and len(err.strip().splitlines()) == 1
    assert main(["cache", "clear", "--kind", "factor3d"]) == 0       # a real kind with no entries: nothing to do
    assert "no entries of kind factor3d" in capsys.readouterr().out


def test_cell_says_a_bad_sim_mesh_as_its_option(tmp_path, capsys):
    assert main(["plan", "paper", "--out", str(tmp_path / "plan.json")]) == 0
    capsys.readouterr()
    rc = cell.main(["--sim", "--plan", str(tmp_path / "plan.json"), "--sim-mesh-m", "0.5", "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("palpate-cell: --sim-mesh-m 0.5: ") and "larger than half the tissue" in err
    assert not (tmp_path / "r" / "probes.jsonl").exists()


def test_a_prior_file_edited_between_runs_is_another_run(tmp_path):
    """The prior was compared by its path: a run resumed on a prior file edited since (another stiffness) mixed
    the two beliefs' rounds. Its content key is kept now, as the scene's."""
    prior = tmp_path / "belief.toml"
    prior.write_text('''name = "belief"
[tissue]
width_m = 0.07
height_m = 0.05
youngs_pa = 2500.0
poisson = 0.4
''')
    def opts(path):
        args = build_parser("run").parse_args(["run", "paper", "--sim", "--prior", str(path), "--out", "x"])
        return run_options(args, load("paper"), None, load(str(path)).prior())
    first = opts(prior)
    out = tmp_path / "run"
    out.mkdir()
    (out / "run_options.json").write_text(json.dumps(first))
    (out / "probes.jsonl").write_text("")
    copy = tmp_path / "copy.toml"
    copy.write_text(prior.read_text())
    assert check_resume(out, opts(copy), fresh=False)              # the same content by another path resumes
    prior.write_text(prior.read_text().replace("2500.0", "1800.0"))
    with pytest.raises(UsageError, match="prior_key was"):
        check_resume(out, opts(prior), fresh=False)
    older = {k: v for k, v in first.items() if k != "prior_key"}   # a run kept before the key: the path decides
    (out / "run_options.json").write_text(json.dumps(older))
    assert check_resume(out, opts(prior), fresh=False)


def test_fresh_refuses_an_input_that_is_one_of_the_runs_own_files(tmp_path, capsys):
    """`--fresh --plan OUT/plan_round1.json` kept that file in OUT as the command's input; the new run then took it
    for its own round 1 (the coarse raster again in place of the refinement)."""
    out = tmp_path / "run"
    out.mkdir()
    assert main(["plan", "paper", "--out", str(out / "plan_round1.json")]) == 0
    (out / "probes.jsonl").write_text("")
    (out / "run_options.json").write_text("{}")
    capsys.readouterr()
    rc = main(["run", "paper", "--sim", "--plan", str(out / "plan_round1.json"), "--fresh", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and "--plan " in err and "copy it out of" in err
    assert sorted(p.name for p in out.iterdir()) == ["plan_round1.json", "probes.jsonl", "run_options.json"]
