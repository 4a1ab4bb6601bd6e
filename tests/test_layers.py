"""The layer rule (docs/architecture.md): every import in gca/ and stages/ points down the layer order, and no
group of modules imports itself in a loop (imports inside functions count too)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: bottom to top; a module may import its own package and anything on a lower layer, nothing beside or above.
LAYERS = (
    ("core", ("gca", "gca.config", "gca.io", "gca.warp_stream", "gca.gpu_slot", "gca.efficiency", "gca.linalg",
              "gca.sh", "gca.stop", "gca.stamp")),
    ("assets", ("gca.assets",)),
    ("laws", ("gca.laws",)),
    ("sim", ("gca.sim",)),
    ("render", ("gca.render",)),
    ("capture", ("gca.capture",)),
    ("vision", ("gca.vision",)),
    ("scenes", ("gca.scenes",)),
    ("align", ("gca.align",)),
    ("train", ("gca.train",)),
    ("eval", ("gca.eval",)),
    ("report", ("gca.report",)),
    ("pipeline", ("gca.pipeline",)),
    ("stages", ("stages",)),
)


def layer_of(module: str) -> int:
    """Index into LAYERS of a dotted module name (the longest matching prefix); KeyError if none."""
    best = None
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and (best is None or len(p) > best[1]):
                best = (i, len(p))
    if best is None:
        raise KeyError(module)
    return best[0]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path) -> list[tuple[str, int]]:
    """(imported gca/stages module, line) for every import statement in the file, at any depth."""
    mod = module_name(path)
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            # `from gca import config` imports the module gca.config; `from gca.x import name` imports gca.x
            names = [f"{base}.{a.name}" if _is_module(f"{base}.{a.name}") else base for a in node.names]
        else:
            continue
        found += [(n, node.lineno) for n in names if n.split(".")[0] in ("gca", "stages")]
    return found


def _is_module(dotted: str) -> bool:
    p = ROOT.joinpath(*dotted.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def sources() -> list[Path]:
    return sorted(ROOT.glob("gca/**/*.py")) + sorted(ROOT.glob("stages/*.py"))


def test_every_module_has_a_layer():
    assert [module_name(p) for p in sources() if _no_layer(module_name(p))] == []


def _no_layer(mod):
    try:
        layer_of(mod)
        return False
    except KeyError:
        return True


def _package(mod: str) -> str:
    """The unit of the layer rule: gca.<package> (a top-level core module is its own), stages."""
    parts = mod.split(".")
    return ".".join(parts[:2]) if parts[0] == "gca" else parts[0]


def violations(edges) -> list[str]:
    """Imports that point up or sideways between packages: 'file:line: a (layer) imports b (layer)'."""
    bad = []
    for path, mod, target, line in edges:
        i, j = layer_of(mod), layer_of(target)
        if j > i or (j == i and _package(mod) != _package(target) and LAYERS[i][0] != "core"):
            bad.append(f"{path.relative_to(ROOT)}:{line}: {mod} ({LAYERS[i][0]}) imports {target} ({LAYERS[j][0]})")
    return bad


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


@pytest.fixture(scope="module")
def edges():
    return [(p, module_name(p), target, line) for p in sources() for target, line in imports(p)
            if module_name(p) != target]


def test_imports_point_down_the_layers(edges):
    assert violations(edges) == []


def test_no_import_cycles(edges):
    graph = {}
    for _, mod, target, _ in edges:
        if not target.startswith(mod + "."):  # a package's face importing its own modules is no cycle
            graph.setdefault(mod, set()).add(target)
    assert cycles(graph) == []


def test_the_checks_catch_an_upward_import_and_a_cycle(tmp_path):
    """Negative controls: the two rules fire on the shapes they exist for."""
    fake = ROOT / "gca" / "sim" / "x.py"
    assert violations([(fake, "gca.sim.x", "gca.train.loop", 3)]) == [
        "gca/sim/x.py:3: gca.sim.x (sim) imports gca.train.loop (train)"]
    assert violations([(fake, "gca.assets.x", "gca.laws.base", 1)])  # sideways between packages of one layer
    assert violations([(fake, "gca.eval.x", "gca.sim.rollout", 1), (fake, "gca.config", "gca.io", 1)]) == []
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
