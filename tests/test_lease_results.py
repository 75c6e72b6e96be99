"""scripts/lease_results.py: a budget's worth of a results table's missing runs, trained on the
CPU at tiny sizes against a fake folder of committed runs; only finished runs come back."""
from __future__ import annotations

import json
import os
import tarfile

import pytest

from conftest import REPO, load_script, make_run, tiny_overrides
from imssr.rundir import FINISHED, RunDir

lease = load_script("scripts/lease_results.py")

TINY = ["train.seed_steps=60", "train.burst_updates=0", *tiny_overrides(), "train.replay_capacity=1000",
        "train.eval_every_steps=125", "train.eval_episodes=1", "train.checkpoint_every_steps=0"]


def _plan(tmp_path, steps=250, seeds="1-3", runs="table/runs/fp32"):
    """A plan of one step (CURL and IM-CURL on cartpole_swingup at ``steps`` agent steps) in
    ``tmp_path``: returns the plan file and the folder of its committed runs."""
    (tmp_path / "table").mkdir(exist_ok=True)
    (tmp_path / "table" / "sweep.json").write_text(json.dumps(
        {"algos": ["curl", "im-curl"], "tasks": ["cartpole_swingup"], "seeds": "1-3", "steps": steps, "set": TINY}))
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"steps": [{"sweep": "table/sweep.json", "runs": runs, "seeds": seeds}]}))
    return str(plan), tmp_path / runs


def _main(*argv):
    return lease.main([*argv, "--device", "cpu", "--threads", "1", "--set", "train.env_workers=false", "--poll", "0.5"])


def _files(out):
    return sorted(os.path.relpath(os.path.join(d, f), out) for d, _, fs in os.walk(out) for f in fs)


def test_a_lease_trains_the_missing_runs_in_order_and_packs_each_finished_one(tmp_path, capsys):
    plan, committed = _plan(tmp_path, steps=125)
    # Committed: CURL and IM-CURL seed 1 at their budget; CURL seed 2 cut short (left alone, named).
    for algo, seed, last in (("curl", 1, 125), ("im-curl", 1, 125), ("curl", 2, 100)):
        make_run(str(committed), algo, seed, [("training", last, 100.0)], task="cartpole_swingup", steps=125)
    before = (committed / "cartpole_swingup" / "curl" / "seed_2" / "eval.csv").read_bytes()
    out, work = tmp_path / "out", tmp_path / "work"
    assert _main("--plan", plan, "--budget", "900", "--out", str(out), "--work", str(work), "--max-runs", "2",
                 "--runs-per-process", "2", "--reserve", "10") == 0
    assert _files(out) == ["lease.md", "results.tar.gz", "train.log"]
    with tarfile.open(out / "results.tar.gz") as tar:
        names = sorted(tar.getnames())
        evals = {name: tar.extractfile(name).read().decode() for name in names if name.endswith("/eval.csv")}
    # The next two missing runs in order (IM-CURL seed 2, then CURL seed 3), in one process, and
    # each one's exported files under the plan's folder for them: nothing else.
    expected = sorted(f"table/runs/fp32/cartpole_swingup/{run}/{name}"
                      for run in ("im-curl/seed_2", "curl/seed_3")
                      for name in ("config.json", "provenance.json", "train.csv", "eval.csv", "eval_episodes.csv"))
    assert names == expected
    for text in evals.values():
        assert text.splitlines()[-1].split(",")[1] == "125"  # its evaluation at the budget
    report = (out / "lease.md").read_text()
    assert "2 run(s) started, 2 finished and packed" in report
    assert "table/runs/fp32/cartpole_swingup/curl/seed_2 is there but did not reach its budget" in report
    assert (committed / "cartpole_swingup" / "curl" / "seed_2" / "eval.csv").read_bytes() == before
    # What the archive holds makes the plan complete up to those runs.
    with tarfile.open(out / "results.tar.gz") as tar:
        tar.extractall(tmp_path, filter="data")
    todo, _ = lease.missing(*lease.read_plan(plan))
    assert [c.name for c in todo] == ["im-curl cartpole_swingup seed 3"]


def test_a_run_that_cannot_finish_in_the_budget_is_never_packed(tmp_path):
    plan, _ = _plan(tmp_path, steps=100_000, seeds="1")
    out, work = tmp_path / "out", tmp_path / "work"
    # The budget ends 10 s in (40 s less 30 s to stop and pack): 100,000 agent steps are far off.
    assert _main("--plan", plan, "--budget", "40", "--out", str(out), "--work", str(work), "--max-runs", "1",
                 "--reserve", "5") == 0
    assert _files(out) == ["lease.md", "train.log"]
    report = (out / "lease.md").read_text()
    assert "1 run(s) started, 0 finished and packed" in report and "not finished (the budget ended)" in report
    run = RunDir(str(work / "step1" / "cartpole_swingup" / "curl" / "seed_1"))
    assert run.status() != FINISHED and run.read_done() is None


def test_the_pace_comes_from_episodes_of_updates_and_the_evaluations_between_them():
    # Seed phase to step 100 (fast), then 1 s per agent step; an evaluation at 300 costs 20 s.
    rows = [lease.Row(s, w) for s, w in ((50, 10.0), (100, 12.0), (200, 112.0), (300, 232.0), (400, 332.0))]
    measured = lease.pace(rows, since=0.0, learning=100, every=300)
    assert (measured.step_s, measured.eval_s, measured.samples) == (1.0, 20.0, 2)
    assert lease.pace(rows, since=150.0, learning=100, every=300).samples == 1  # episodes before `since` left out
    assert lease.pace(rows[:2], since=0.0, learning=100, every=300) is None  # the seed phase gives no pace
    # Evaluations left after agent step 1,000 of 12,500 every 1,250: 1,250 ... 12,500 (the final one).
    assert lease.evaluations_left(1000, 12500, 1250) == 10
    assert lease.evaluations_left(1000, 1100, 1250) == 1  # only the final one, off the schedule
    assert lease.evaluations_left(1000, 1000, 0) == 0
    assert lease.seconds_left(rows[-1], 500, 300, 1.0, 20.0) == 100 + 20


def test_the_lease_keeps_the_longest_prefix_that_finishes():
    def outlooks(*left):
        return [lease.Outlook(lease.Row(1000, 100.0), s) for s in left]

    assert lease.keep_how_many(outlooks(300, 300, 300), now=100.0, deadline=400.0, margin=0.0) == 3
    # 600 s each at 3 processes: 2 of them take 400 s, 1 alone 200 s.
    assert lease.keep_how_many(outlooks(600, 600, 600), now=100.0, deadline=500.0, margin=0.0) == 2
    assert lease.keep_how_many(outlooks(600, 600, 600), now=100.0, deadline=300.0, margin=0.0) == 1
    assert lease.keep_how_many(outlooks(600, 600, 600), now=100.0, deadline=250.0, margin=0.0) == 0
    assert lease.keep_how_many(outlooks(300, 300, 300), now=100.0, deadline=400.0, margin=0.1) == 2


def test_the_committed_plan_reads_and_says_what_each_step_has(capsys):
    assert lease.main(["--plan", os.path.join(REPO, "docs", "results", "lease_plan.json"), "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "dmc100k_cartpole_swingup/runs/fp32 (cartpole_swingup): curl 3/10, im-curl 3/10" in text
    assert "next: curl cartpole_swingup seed 4 (dmc100k_cartpole_swingup/runs/fp32), im-curl cartpole_swingup seed 4" \
        in text


@pytest.mark.parametrize("step, message", [
    ({"sweep": "table/sweep.json", "runs": "../elsewhere"}, "must be a folder inside the plan's folder"),
    ({"sweep": "table/sweep.json", "runs": "r", "seed": "1"}, 'must be an object with "sweep" and "runs"'),
    ({"sweep": "table/none.json", "runs": "r"}, "none.json"),
])
def test_a_bad_plan_is_one_line(tmp_path, capsys, step, message):
    _plan(tmp_path)
    (tmp_path / "bad.json").write_text(json.dumps({"steps": [step]}))
    assert lease.main(["--plan", str(tmp_path / "bad.json"), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lease_results: error: ") and message in err and err.count("\n") == 1
