"""A grid's timeline from its log (``gca.pipeline.timeline``): spans in grid time over calls, a stopped job's bar per
call, midnight, lines that are no grid lines, the summary, the plot, and ``grid.collect`` writing it."""

from __future__ import annotations

import tarfile

import pytest

from gca.pipeline import grid, timeline

LOG = """\
[grid 23:59:00] 5 jobs (5 to run) through local on GPU(s) 1 x 2 slots, profile paper
[grid 23:59:00] --mps: CUDA MPS daemon started
[grid 23:59:00] start inputs@ball on gpu 0 (log x)
[grid 23:59:40] done  inputs@ball in 40 s
[grid 23:59:40] start train@ball:nclaw@seed1 on gpu 0 (log x)
[grid 23:59:41] start train@ball:gca on gpu 0 (log x)
[grid 00:00:10] FAIL  train@ball:nclaw@seed1 (exit 1) after 30 s; log: x
Traceback (most recent call last):
  a failed job's log tail: not a grid line
[grid 00:01:00] stop  train@ball:gca at the deadline (resumes next time)
[grid 00:01:02] after 122 s: {'done': 1, 'todo': 1}; run the same command again to go on
[grid 00:01:02] results: out/grid_results.tar.gz
[grid 00:05:00] 5 jobs (1 to run) through local on GPU(s) 1 x 2 slots, profile paper
[grid 00:05:01] start train@ball:gca on gpu 0 (log x)
[grid 00:06:01] done  train@ball:gca in 60 s
[grid 00:06:02] start evaluate@ball:gca on gpu 0 (log x)
"""


def test_spans_are_in_grid_time_over_calls_and_midnight():
    tl = timeline.parse(LOG.splitlines())
    assert tl.calls == [(0.0, 122.0), (122.0, 184.0)]  # 23:59:00 -> 00:01:02; the 4-min gap between calls left out
    got = [(s.job, s.start, s.end, s.how, s.call) for s in tl.spans]
    assert got == [("inputs@ball", 0.0, 40.0, "done", 0), ("train@ball:nclaw@seed1", 40.0, 70.0, "FAIL", 0),
                   ("train@ball:gca", 41.0, 120.0, "stop", 0), ("train@ball:gca", 123.0, 183.0, "done", 1),
                   ("evaluate@ball:gca", 184.0, 184.0, "open", 1)]  # the log ends with it running
    assert timeline.running(tl, 50.0) == 2 and timeline.running(tl, 50.0, ("train:gca",)) == 1
    assert timeline.running(tl, 121.0) == 0


def test_kinds_and_summary():
    jobs = ["inputs@ball", "object@duck", "train@ball:nclaw@seed2", "train@ball:gca@seed1", "train@ball:neuma",
            "train@ball:no_cpr", "evaluate@ball:gca", "report", "demo@x"]
    assert [timeline.kind(j) for j in jobs] == ["inputs", "inputs", "fit", "train:gca", "train:neuma", "train",
                                                "evaluate", "report", "other"]
    info = timeline.summary(timeline.parse(LOG.splitlines()))
    assert info["grid_seconds"] == 184.0 and info["calls_seconds"] == [122.0, 62.0]
    assert info["job_seconds"] == {"evaluate": 0.0, "fit": 30.0, "inputs": 40.0, "train:gca": 139.0}
    assert info["stopped"] == 1 and info["failed"] == ["train@ball:nclaw@seed1"] and info["jobs"] == 4
    assert info["mean_running"] == [round(149 / 122, 2), round(60 / 62, 2)]


def test_the_plot_is_written_and_a_log_without_grid_lines_says_so(tmp_path, capsys):
    log = tmp_path / "grid.log"
    log.write_text(LOG)
    info = timeline.from_log(log, tmp_path / "t.png")
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and info["jobs"] == 4
    bad = tmp_path / "bad.log"
    bad.write_text("not a grid log\n")
    with pytest.raises(SystemExit, match=r"bad\.log: no grid log lines"):
        timeline.main([str(bad), str(tmp_path / "b.png")])
    assert not (tmp_path / "b.png").exists()
    with pytest.raises(SystemExit, match="no such grid log"):
        timeline.main([str(tmp_path / "none.log"), str(tmp_path / "b.png")])
    assert timeline.main([str(log), str(tmp_path / "c.png"), "--json", str(tmp_path / "c.json")]) == 0
    assert "4 jobs, 184 s of grid time in 2 call(s), 1 stopped" in capsys.readouterr().out


def test_collect_writes_the_timeline_beside_the_archive(tmp_path):
    (tmp_path / ".grid").mkdir()
    (tmp_path / ".grid" / "grid.log").write_text(LOG)
    with tarfile.open(grid.collect(tmp_path, tmp_path / "out")) as tar:
        assert ".grid/grid.log" in tar.getnames()
    assert (tmp_path / "out" / "timeline.png").is_file()
    (tmp_path / ".grid" / "grid.log").write_text("")  # a grid that logged nothing yet: the archive, no plot
    grid.collect(tmp_path, tmp_path / "out2")
    assert (tmp_path / "out2" / "grid_results.tar.gz").is_file() and not (tmp_path / "out2" / "timeline.png").exists()


def test_slurm_lines_before_commands_a_killed_call_and_a_job_done_as_it_was_stopped():
    """SLURM's start lines lack " on <place>" (and a re-attached job logs "attach"); --before's line precedes its
    call's "N jobs" line (its time is not grid time, and it ends a call killed without its "after" line); a job
    that finished on the stop's signal ("done X as it was stopped") counts done; a skipped job's span ends there."""
    log = """\
[grid 10:00:00] before: make something
[grid 10:00:30] 3 jobs (3 to run) through slurm on SLURM, profile paper
[grid 10:00:30] start train@ball:gca (log /l/1)
[grid 10:00:31] attach train@ball:neuma (log /l/2)
[grid 10:00:32] start evaluate@ball:nclaw (log /l/3)
[grid 10:01:00] FAIL  train@ball:neuma (exit 1) after 29 s; log: /l/2
[grid 10:01:00] skip  evaluate@ball:neuma: train@ball:neuma failed
[grid 10:01:10] stop  train@ball:gca at the deadline (resumes next time)
[grid 10:01:12] done  train@ball:gca as it was stopped
[grid 15:00:00] before: make something
[grid 15:00:20] 3 jobs (1 to run) through slurm on SLURM, profile paper
[grid 15:00:20] start report (log /l/4)
[grid 15:00:50] done  report in 30 s
[grid 15:00:51] after 31 s: {'done': 3}; nothing left to run
"""
    tl = timeline.parse(log.splitlines())
    assert tl.calls == [(0.0, 42.0), (42.0, 73.0)]  # killed at 10:01:12; the 5-h gap and --before's 20-30 s left out
    got = [(s.job, s.start, s.end, s.how) for s in tl.spans]
    assert got == [("train@ball:gca", 0.0, 40.0, "done"), ("train@ball:neuma", 1.0, 30.0, "FAIL"),
                   ("evaluate@ball:nclaw", 2.0, 42.0, "open"), ("report", 42.0, 72.0, "done")]
    assert timeline.summary(tl)["stopped"] == 0


def test_a_log_of_calls_without_jobs_plots_and_collect_survives_a_plot_that_fails(tmp_path, monkeypatch, capsys):
    log = tmp_path / "grid.log"
    log.write_text("[grid 10:00:00] 3 jobs (0 to run) through local on GPU(s) 1 x 2 slots, profile paper\n"
                   "[grid 10:00:00] after 0 s: {'done': 3}; nothing left to run\n")
    assert timeline.from_log(log, tmp_path / "t.png")["jobs"] == 0 and (tmp_path / "t.png").is_file()
    (tmp_path / ".grid").mkdir()
    (tmp_path / ".grid" / "grid.log").write_text(LOG)

    def broken(*args, **kwargs):
        raise RuntimeError("no display")
    monkeypatch.setattr(timeline, "plot", broken)
    assert grid.collect(tmp_path, tmp_path / "out").is_file()
    assert "timeline: no plot (RuntimeError: no display)" in capsys.readouterr().out
