"""The pytest markers are applied by rule, not by memory: every test that runs a float64 gradcheck (directly or
through a helper of its file) carries ``grad``; every test skipped where torch sees no CUDA device carries ``gpu``
(the device bundles select the CUDA tests with ``-m gpu``; session 52's selected none of a file whose CUDA tests were
only skipped); only registered markers exist (``--strict-markers``); the slow list (``tests/slow.txt``, measured)
names tests that exist."""

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent
GRAD_CALLS = {"gradcheck", "gradgradcheck"}


def _called(node: ast.AST) -> set[str]:
    return {(c.func.attr if isinstance(c.func, ast.Attribute) else getattr(c.func, "id", ""))
            for c in ast.walk(node) if isinstance(c, ast.Call)}


def grad_tests(tree: ast.Module) -> dict[str, bool]:
    """Test name -> whether it is marked ``grad``, for the tests of a module that reach a gradcheck call."""
    funcs = {n.name: n for n in tree.body if isinstance(n, ast.FunctionDef)}
    reach = set(GRAD_CALLS)
    while True:  # helpers calling helpers calling gradcheck
        grown = {name for name, f in funcs.items() if _called(f) & reach} | GRAD_CALLS
        if grown == reach:
            break
        reach = grown
    return {name: any("mark.grad" in ast.unparse(d) for d in f.decorator_list)
            for name, f in funcs.items() if name.startswith("test_") and name in reach}


def test_every_gradcheck_test_is_marked_grad():
    unmarked = [f"{p.name}::{name}" for p in sorted(TESTS.glob("test_*.py"))
                for name, marked in grad_tests(ast.parse(p.read_text())).items() if not marked]
    assert unmarked == []


def test_the_rule_sees_a_gradcheck_behind_a_helper():
    """Negative control: an unmarked test reaching gradcheck through a helper is found; a marked one is not."""
    tree = ast.parse("def _check(f):\n    gradcheck(f, ())\n\ndef test_a():\n    _check(None)\n\n"
                     "@pytest.mark.grad\ndef test_b():\n    gradcheck(None, ())\n\ndef test_c():\n    pass\n")
    assert grad_tests(tree) == {"test_a": False, "test_b": True}


def cuda_skipped_tests(tree: ast.Module) -> dict[str, bool]:
    """Test name -> whether it is marked ``gpu``, for the tests of a module skipped whole by a ``skipif`` on
    ``torch.cuda.is_available()`` (a CUDA case among parameters carries its marks itself: ``pytest.param``)."""
    return {f.name: any("mark.gpu" in ast.unparse(d) for d in f.decorator_list)
            for f in tree.body if isinstance(f, ast.FunctionDef) and f.name.startswith("test_")
            and any(ast.unparse(d).startswith("pytest.mark.skipif") and "cuda.is_available" in ast.unparse(d)
                    for d in f.decorator_list)}


def test_every_test_skipped_without_cuda_is_marked_gpu():
    unmarked = [f"{p.name}::{name}" for p in sorted(TESTS.glob("test_*.py"))
                for name, marked in cuda_skipped_tests(ast.parse(p.read_text())).items() if not marked]
    assert unmarked == []


def test_the_gpu_rule_sees_an_unmarked_cuda_test():
    """Negative control: a CUDA-skipped test without ``gpu`` is found, a marked one and a plain one are not, nor one
    whose CUDA case is a parameter's."""
    skip = '@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")\n'
    param = ('@pytest.mark.parametrize("d", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif('
             'not torch.cuda.is_available(), reason="x"))])\n')
    tree = ast.parse(f"{skip}def test_a():\n    pass\n\n@pytest.mark.gpu\n{skip}def test_b():\n    pass\n\n"
                     f"def test_c():\n    pass\n\n{param}def test_d(d):\n    pass\n")
    assert cuda_skipped_tests(tree) == {"test_a": False, "test_b": True}


def test_markers_are_strict_and_the_slow_list_is_real(pytestconfig):
    assert pytestconfig.getoption("strict_markers") or "--strict-markers" in pytestconfig.getini("addopts")
    names = {f"{p.name}::{n.name}" for p in TESTS.glob("test_*.py") for n in ast.parse(p.read_text()).body
             if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")} | {p.name for p in TESTS.glob("test_*.py")}
    listed = [line.split("#")[0].strip() for line in (TESTS / "slow.txt").read_text().splitlines()]
    assert [t for t in listed if t and t not in names] == []

