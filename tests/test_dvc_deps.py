"""dvc.yaml's deps cover what each stage runs: every file of the stage script's transitive imports (gca and
stages modules, imports inside functions too, each package's __init__ on the way) lies under one of its deps.
A missing dep means an edited module does not re-run the stage, and the tables go stale silently."""

from pathlib import Path

import pytest
import yaml

from test_layers import ROOT, imports, module_name, sources

DVC = yaml.safe_load((ROOT / "dvc.yaml").read_text())


def module_file(mod: str) -> Path:
    p = ROOT.joinpath(*mod.split("."))
    return p.with_suffix(".py") if p.with_suffix(".py").is_file() else p / "__init__.py"


def closure(script: Path) -> set[Path]:
    """The .py files a stage script loads: its gca/stages imports, transitively, with the parents' __init__."""
    by_name = {module_name(p): p for p in sources()}
    todo, seen = [module_name(script)], set()
    while todo:
        mod = todo.pop()
        if mod in seen:
            continue
        seen.add(mod)
        parts = mod.split(".")
        todo += [".".join(parts[:k]) for k in range(1, len(parts)) if ".".join(parts[:k]) in by_name]
        todo += [t for t, _ in imports(by_name[mod]) if t in by_name]
    return {module_file(m).relative_to(ROOT) for m in seen}


def uncovered(files: set[Path], deps: list[str]) -> list[str]:
    """Files under no dep (a dep is a file or a folder)."""
    return sorted(str(f) for f in files if not any(f == Path(d) or Path(d) in f.parents for d in deps))


def stage_defs():
    for name, stage in DVC["stages"].items():
        body = stage.get("do", stage)
        script = ROOT / body["cmd"].split()[1]
        yield name, script, [d for d in body["deps"] if not d.startswith(("data/", "models/", "runs/", "metrics/"))]


@pytest.mark.parametrize("name,script,deps", list(stage_defs()), ids=[n for n, _, _ in stage_defs()])
def test_stage_deps_cover_its_imports(name, script, deps):
    assert uncovered(closure(script), deps) == []


def test_every_dep_exists():
    missing = [(n, d) for n, _, deps in stage_defs() for d in deps if not (ROOT / d).exists()]
    assert missing == []


def test_the_check_sees_a_missing_module():
    """Negative control: the train stage loads gca/assets/particles.py (through the scene's body); without a
    dep on it the check reports exactly that file."""
    files = closure(ROOT / "stages" / "train.py")
    assert Path("gca/assets/particles.py") in files and Path("gca/__init__.py") in files
    assert uncovered({Path("gca/assets/particles.py"), Path("gca/sim/rollout.py")}, ["gca/sim"]) == [
        "gca/assets/particles.py"]
