"""A grid's chain of a scene's input stages in one job (``gca.pipeline.grid.chain_inputs``) run in one process
(``gca.pipeline.chain``): which jobs join, what waits on the chain, the runner's markers, failures and stops, and the
chained stages' outputs byte for byte against each stage in its own process (CI profile)."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import shlex
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from gca.pipeline import chain, dispatch, grid

ROOT = Path(__file__).resolve().parents[1]
STAGES = ["assets", "particles", "prior", "ground_truth", "preprocess", "nuisance", "train", "evaluate", "report"]


def _jobs(scenes=("ball", "cat"), params=None):
    params = params or grid.grid_params("ci", list(scenes), ["gca", "nclaw"], [])
    dvc = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    return params, grid.link(grid.split_runs(grid.expand(dvc, params, STAGES), params))


def test_a_scenes_inputs_are_one_chain_job_and_its_readers_wait_on_it():
    params, jobs = _jobs()
    chained = grid.chain_inputs(jobs, params)
    ball = chained["inputs@ball"]
    assert ball.members == ["assets@ball", "particles@ball", "ground_truth@ball", "preprocess@ball"]
    assert not set(ball.members) & set(chained) and "inputs@cat" in chained
    assert ball.cmd.startswith("python -m gca.pipeline.chain assets@ball 'python stages/assets.py --object ball")
    assert [name for name, _ in chain.pairs(shlex.split(ball.cmd)[3:])] == ball.members
    assert ball.after == set() and ball.cost == pytest.approx(sum(jobs[m].cost for m in ball.members))
    assert {"data/assets/ball", "data/prep/ball"} <= set(ball.outs)
    # what read a member waits on the chain; what else it waited on stays
    assert chained["train@ball:gca"].after == {"inputs@ball", "prior@jelly", "train@ball:nclaw"}
    assert chained["nuisance@ball"].after == {"inputs@ball"}
    assert {"inputs@ball", "train@ball:gca"} <= chained["evaluate@ball:gca"].after
    assert not any(m in j.after for j in chained.values() for m in ball.members)
    prio = dispatch.critical_path(chained)
    assert prio["inputs@ball"] > prio["train@ball:gca"] > prio["report"]
    # negative control: the jobs given are not changed in place
    assert "assets@ball" in jobs["train@ball:gca"].after and jobs["train@ball:gca"].after != chained["train@ball:gca"].after


def test_the_first_seeds_velocity_fit_ends_the_chain_where_the_prior_is_there_already():
    """With the priors given (no prior job: Table 1's grid), the chain ends with the first seed's launch-velocity fit
    (NCLaw's training job); the other seeds' fits stay their own jobs, run beside each other."""
    params = grid.grid_params("ci", ["ball"], ["gca", "nclaw"], ["train.seeds=[0,1]"])
    _, jobs = _jobs(params=params)
    without_prior = {n: dataclasses.replace(j, after={a for a in j.after if not a.startswith("prior@")})
                     for n, j in jobs.items() if not n.startswith("prior@")}  # as the grid's --priors leaves them
    chained = grid.chain_inputs(without_prior, params)
    assert chained["inputs@ball"].members == ["assets@ball", "particles@ball", "ground_truth@ball", "preprocess@ball",
                                             "train@ball:nclaw"]
    assert "runs/ball/velocity.json" in chained["inputs@ball"].outs
    assert chained["train@ball:gca"].after == {"inputs@ball"}
    assert chained["train@ball:nclaw@seed1"].after == {"inputs@ball"}  # its own fit, beside the chain's next jobs
    assert chained["train@ball:gca@seed1"].after == {"inputs@ball", "train@ball:nclaw@seed1"}
    assert grid.velocity_job(without_prior, "ball") == "train@ball:nclaw" and grid.velocity_job(without_prior, "cat") is None
    # negative control: the prior still to be made, the fit waits on it: the chain ends at the preprocessing
    with_prior = grid.chain_inputs(jobs, params)
    assert with_prior["inputs@ball"].members[-1] == "preprocess@ball" and "train@ball:nclaw" in with_prior


def test_done_members_stay_out_and_a_chain_of_one_is_no_chain():
    params, jobs = _jobs(("ball",))
    chained = grid.chain_inputs(jobs, params, done={"assets@ball", "particles@ball"}, stamp="abc")
    assert chained["inputs@ball"].members == ["ground_truth@ball", "preprocess@ball"]
    assert chained["inputs@ball"].cmd.startswith("python -m gca.pipeline.chain --stamp abc ground_truth@ball ")
    assert chained["inputs@ball"].after == {"assets@ball", "particles@ball"}  # done: the dispatcher passes them
    one = grid.chain_inputs(jobs, params, done={"assets@ball", "particles@ball", "ground_truth@ball"})
    assert "inputs@ball" not in one and one["preprocess@ball"].cmd == jobs["preprocess@ball"].cmd
    assert one["train@ball:gca"].after == jobs["train@ball:gca"].after


def test_chain_undone_reads_the_markers_of_this_stamp_only(tmp_path):
    params, jobs = _jobs(("ball",))
    dispatch.write_done(tmp_path, "assets@ball", 1.0, "abc")
    dispatch.write_done(tmp_path, "particles@ball", 1.0, "old")  # another grid's inputs: not done here
    chained = grid.chain_undone(jobs, params, tmp_path, "abc")
    assert chained["inputs@ball"].members == ["particles@ball", "ground_truth@ball", "preprocess@ball"]
    assert chained == grid.chain_inputs(jobs, params, done={"assets@ball"}, stamp="abc")


def test_scenes_sharing_an_object_make_it_once_then_each_scene_its_own():
    params = grid.grid_params("ci", ["ball", "cat"], ["nclaw"], [])
    params["scenes"]["cat"]["object"] = "ball"  # two scenes of one object
    params["objects"] = {"ball": params["objects"]["ball"]}
    _, jobs = _jobs(params=params)
    chained = grid.chain_inputs(jobs, params)
    assert chained["object@ball"].members == ["assets@ball", "particles@ball"]
    assert chained["inputs@ball"].members == ["ground_truth@ball", "preprocess@ball"]
    assert chained["inputs@cat"].members == ["ground_truth@cat", "preprocess@cat"]
    assert chained["inputs@cat"].after == {"object@ball"} == chained["inputs@ball"].after
    assert grid.input_chains({"scenes": "not a mapping"}) == [] and grid.input_chains({}) == []  # --repo: not ours


def test_a_member_waiting_on_a_job_outside_the_chain_ends_it():
    J = grid.Job
    jobs = {"assets@o": J("assets@o", "python a.py", [], ["a"], 1.0),
            "particles@o": J("particles@o", "python b.py", ["a"], ["b"], 1.0, {"assets@o"}),
            "elsewhere": J("elsewhere", "python e.py", [], ["e"], 1.0),
            "ground_truth@s": J("ground_truth@s", "python c.py", ["b", "e"], ["c"], 1.0, {"particles@o", "elsewhere"}),
            "preprocess@s": J("preprocess@s", "python d.py", ["c"], ["d"], 1.0, {"ground_truth@s"})}
    chained = grid.chain_inputs(jobs, {"scenes": {"s": {"object": "o"}}})
    assert chained["inputs@s"].members == ["assets@o", "particles@o"]  # the ground truth waits on `elsewhere` too
    assert chained["ground_truth@s"].after == {"inputs@s", "elsewhere"} and chained["preprocess@s"].after == {"ground_truth@s"}
    done = grid.chain_inputs(jobs, {"scenes": {"s": {"object": "o"}}}, done={"elsewhere"})
    assert done["inputs@s"].members == ["assets@o", "particles@o", "ground_truth@s", "preprocess@s"]  # control


def test_a_chains_state_goes_to_its_members_for_dvc_commit():
    params, jobs = _jobs(("ball",))
    chained = grid.chain_inputs(jobs, params)
    state = {n: "done" for n in chained}
    state["train@ball:gca"] = "failed"
    members = grid.members_state(state, chained)
    assert "inputs@ball" not in members and members["ground_truth@ball"] == "done"
    stages = dispatch.dvc_stages(members)
    assert {"assets@ball", "particles@ball", "ground_truth@ball", "preprocess@ball"} <= set(stages)
    assert "train@ball" not in stages and "inputs@ball" not in dispatch.dvc_stages(members)
    # a chain failed at its ground truth: the members before it finished (their own markers), so their stages commit
    state["inputs@ball"] = "failed"
    cut = grid.members_state(state, chained, lambda m: m in {"assets@ball", "particles@ball"})
    assert cut["assets@ball"] == cut["particles@ball"] == "done" and cut["ground_truth@ball"] == "failed"
    assert {"assets@ball", "particles@ball"} <= set(dispatch.dvc_stages(cut))
    assert not {"ground_truth@ball", "preprocess@ball"} & set(dispatch.dvc_stages(cut))


STAGE = """
import sys, os
from pathlib import Path
from gca.pipeline import cli
from gca.config import ConfigError
import helper  # a module beside the script, as stages/common.py

def main(argv):
    out, how = argv
    if how == "user-error":
        raise ConfigError("params.yaml: knob: not a number")
    if how == "stop":
        from gca import stop
        raise stop.Terminated("stopped (test)")
    Path(out).write_text(f"{os.getpid()} {sys.argv[0]} {helper.NAME}")

if __name__ == "__main__":
    sys.exit(cli.run(main))
"""


def _stages(tmp_path: Path) -> Path:
    folder = tmp_path / "stages"
    folder.mkdir()
    (folder / "helper.py").write_text("NAME = 'helper'\n")
    for name in ("a", "b", "c"):
        (folder / f"{name}.py").write_text(STAGE)
    return folder


def _chain(tmp_path: Path, members, stamp="s1"):
    env = {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    argv = shlex.split(chain.command(members, stamp))
    return subprocess.run([sys.executable, *argv[1:]], cwd=tmp_path, capture_output=True, text=True,
                          env=env, timeout=120)


def test_the_chain_runs_its_stages_in_one_process_and_marks_each_done(tmp_path):
    _stages(tmp_path)
    done = _chain(tmp_path, [("a@x", "python stages/a.py a.txt ok"), ("b@x", "python stages/b.py b.txt ok"),
                             ("sh@x", "sh -c 'echo $$ > sh.txt'")])
    assert done.returncode == 0, done.stderr
    a, b = ((tmp_path / f).read_text().split() for f in ("a.txt", "b.txt"))
    assert a[0] == b[0] and a[1:] == ["stages/a.py", "helper"] and b[1] == "stages/b.py"  # one process, its argv
    assert (tmp_path / "sh.txt").read_text().strip() != a[0]  # a command that is no stage script: a subprocess
    for name in ("a@x", "b@x", "sh@x"):
        assert dispatch.is_done(tmp_path, name, "s1") and not dispatch.is_done(tmp_path, name, "other")
    again = _chain(tmp_path, [("a@x", "python stages/a.py a2.txt ok")])
    assert "a@x: done already" in again.stdout and not (tmp_path / "a2.txt").exists()
    other = _chain(tmp_path, [("a@x", "python stages/a.py a2.txt ok")], stamp="s2")  # other inputs: runs again
    assert other.returncode == 0 and (tmp_path / "a2.txt").is_file()


@pytest.mark.parametrize("how, code", [("user-error", 2), ("stop", 143)])
def test_a_failed_or_stopped_member_ends_the_chain_and_the_next_call_starts_at_it(tmp_path, how, code):
    _stages(tmp_path)
    members = [("a@x", "python stages/a.py a.txt ok"), ("b@x", f"python stages/b.py b.txt {how}"),
               ("c@x", "python stages/c.py c.txt ok")]
    first = _chain(tmp_path, members)
    assert first.returncode == code, first.stderr
    assert "b@x: exit" in first.stderr and not (tmp_path / "c.txt").exists()
    if how == "user-error":
        assert "b: error: params.yaml: knob: not a number" in first.stderr  # the stage's one line, its name
    assert dispatch.is_done(tmp_path, "a@x", "s1") and not dispatch.is_done(tmp_path, "b@x", "s1")
    (tmp_path / "a.txt").unlink()
    members[1] = ("b@x", "python stages/b.py b.txt ok")
    second = _chain(tmp_path, members)
    assert second.returncode == 0 and "a@x: done already" in second.stdout
    assert not (tmp_path / "a.txt").exists() and (tmp_path / "b.txt").is_file() and (tmp_path / "c.txt").is_file()


def test_the_runner_refuses_a_name_without_its_command(tmp_path):
    bad = subprocess.run([sys.executable, "-m", "gca.pipeline.chain", "a@x"], cwd=tmp_path, capture_output=True,
                         text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert bad.returncode == 2 and "expected NAME CMD pairs, got 1" in bad.stderr
    assert chain.stage_script("python stages/a.py --x 1") == (Path("stages/a.py"), ["--x", "1"])
    assert chain.stage_script("python -m gca.x") is None and chain.stage_script("sh -c 'x'") is None


def _digests(work: Path) -> dict[str, str]:
    return {str(p.relative_to(work)): hashlib.sha256(p.read_bytes()).hexdigest()
            for top in ("data", "metrics") for p in sorted((work / top).rglob("*")) if p.is_file()}


def test_chained_inputs_are_byte_for_byte_those_of_one_process_per_stage(tmp_path):
    """The CI profile's ball: assets to preprocess as one chain job, and each stage as its own (``--no-chain``): the
    same files, byte for byte (data and metrics), and the chain is one job where the control has four."""
    argv = ["--scenes", "ball", "--methods", "nclaw", "--profile", "ci", "--gpus", "0", "--slots", "2",
            "--stages", "assets", "particles", "ground_truth", "preprocess"]
    chained = grid.main(["--work", str(tmp_path / "chained"), *argv])
    apart = grid.main(["--work", str(tmp_path / "apart"), *argv, "--no-chain"])
    assert chained == {"inputs@ball": "done"}
    assert apart == {f"{s}@ball": "done" for s in ("assets", "particles", "ground_truth", "preprocess")}
    one, other = _digests(tmp_path / "chained"), _digests(tmp_path / "apart")
    assert len(one) > 20 and any(k.startswith("data/prep/ball/") for k in one)
    assert one == other
    for s in ("assets", "particles", "ground_truth", "preprocess"):  # the members' markers: a later call passes them
        assert dispatch.is_done(tmp_path / "chained", f"{s}@ball")
