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
        yield name, script, [d for d in body["deps"] if d.startswith(("gca/", "stages/"))]


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


def required_deps(script: Path) -> list[str]:
    """The code deps a stage needs: its script, its gca/pipeline and core modules file by file, every other gca
    package it loads as a folder (scripts and core first, as dvc.yaml lists them)."""
    want = set()
    for f in closure(script):
        parts = f.parts
        glue = parts[0] == "stages" or len(parts) == 2 or parts[1] == "pipeline"
        want.add(str(f) if glue else "/".join(parts[:2]))
    order = {"stages": 0, "gca/pipeline": 1}
    return sorted(want, key=lambda d: (order.get(d.rsplit("/", 1)[0], 3 if d.count("/") == 1 else 2), d))


def rewrite_code_deps(text: str) -> str:
    """dvc.yaml text with each stage's code deps (its ``gca/`` and ``stages/`` entries) replaced by
    :func:`required_deps`; every other dep (data, models, a user's captures) is kept after them."""
    import re

    for name, script, _ in stage_defs():
        m = re.search(rf"\n  {name}:\n.*?\n(?P<indent> +)deps:\n", text, re.S)
        indent = m["indent"] + "  "
        lines = text[m.end():].split("\n")
        k = 0
        while lines[k].startswith(indent + "- "):
            k += 1
        kept = [line for line in lines[:k] if not line.strip()[2:].startswith(("gca/", "stages/"))]  # data deps
        text = text[:m.end()] + "\n".join([indent + "- " + d for d in required_deps(script)] + kept + lines[k:])
    return text


if __name__ == "__main__":  # python tests/test_dvc_deps.py: rewrite dvc.yaml's code deps from the imports
    (ROOT / "dvc.yaml").write_text(rewrite_code_deps((ROOT / "dvc.yaml").read_text()))
