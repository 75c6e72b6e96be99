"""imssr report on synthetic sweep directories with known numbers: tables, paper column,
partial sweeps, rliable aggregates, the beta_0 plot, and the CLI."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, TASK, curve, load_script, make_run
from imssr.report.report import write_report
from imssr.sweep.directory import RunStatus, SweepDir
from imssr.sweep.grid import Run
from imssr.training.logger import read_csv


def table(out):
    return {(r["mode"], r["label"], r["fraction"]): r for r in read_csv(os.path.join(out, "table.csv"))}


@pytest.fixture
def paper_csv(tmp_path):
    path = tmp_path / "paper.csv"
    path.write_text("table,task,mode,frames_fraction,algorithm,mean,std\n"
                    f"I,{TASK},training,1.0,CURL,744.2,23.8\nI,{TASK},training,1.0,IM-CURL,744.8,54.2\n")
    return str(path)


def test_table_numbers_bold_and_paper_column(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed, (a, b, c) in zip((1, 2, 3), [(10, 100, 100), (20, 200, 200), (30, 300, 300)]):
        make_run(root, "curl", seed, curve(a, b, c))
    for seed, (a, b, c) in zip((1, 2, 3), [(0, 400, 400), (0, 500, 500), (0, 600, 600)]):
        make_run(root, "im-curl", seed, curve(a, b, c) + curve(1, 2, 3, mode="color_hard"))
    write_report(root, out, paper_results=paper_csv, reps=200)
    t = table(out)
    std = float(np.std([100, 200, 300], ddof=1))  # 100: the sample std
    assert float(t["training", "curl", "1.0"]["mean"]) == 200.0
    assert float(t["training", "curl", "1.0"]["std"]) == pytest.approx(std, rel=1e-5)
    assert float(t["training", "curl", "0.2"]["mean"]) == 20.0  # step 100, not 300
    assert float(t["training", "curl", "0.5"]["mean"]) == 200.0
    # Points in agent steps, their frames beside (action repeat 8).
    assert (t["training", "curl", "1.0"]["step"], t["training", "curl", "1.0"]["frame"]) == ("1000", "8000")
    assert (t["training", "curl", "0.2"]["step"], t["training", "curl", "0.2"]["frame"]) == ("200", "1600")
    assert float(t["training", "im-curl", "1.0"]["mean"]) == 500.0
    assert (t["training", "im-curl", "1.0"]["best"], t["training", "curl", "1.0"]["best"]) == ("1", "0")
    assert (t["training", "curl", "0.2"]["best"], t["training", "im-curl", "0.2"]["best"]) == ("1", "0")
    assert t["training", "curl", "1.0"]["paper_mean"] == "744.2"
    assert t["training", "curl", "0.2"]["paper_mean"] == ""
    # Test scenes get their own table; curl was never evaluated there.
    assert float(t["color_hard", "im-curl", "1.0"]["mean"]) == 3.0
    assert t["color_hard", "curl", "1.0"]["seeds"] == "0"
    md = open(os.path.join(out, "report.md")).read()
    assert "| `cartpole_swingup_sparse` | curl | **20.0** ± 10.0 |  | 200.0 ± 100.0 |  | 200.0 ± 100.0 | 744.2 ± 23.8 | 1: 100.0, 2: 200.0, 3: 300.0 | 3/3 |" in md
    assert "| im-curl | 0.0 ± 0.0 |  | **500.0** ± 100.0 |  | **500.0** ± 100.0 | 744.8 ± 54.2 | 1: 400.0, 2: 500.0, 3: 600.0 | 3/3 |" in md
    # The fixture's published numbers give no seed count: no interval for the difference.
    assert "| `training` | `cartpole_swingup_sparse` | curl | 1.0T | 200.0 ± 100.0 (3) | 744.2 ± 23.8 | " \
           "no interval: the source gives no seed count |" in md
    assert "### `training` (T = 1,000 agent steps)" in md and md.index("### `training`") < md.index("### `color_hard`")
    assert f"| `{TASK}` | 8 | 200 steps (1,600 frames) | 500 steps (4,000 frames) | 1,000 steps (8,000 frames) |" in md
    # The paper's T is 500,000 agent steps; this sweep's points are other steps, and the note says so.
    assert "the paper's numbers are at T = 500,000 agent steps (0.2T/0.5T/1.0T = 100,000/250,000/500,000 " \
           "steps); this sweep's T is 1,000 agent steps" in md
    # Every evaluation, one row each.
    rows = read_csv(os.path.join(out, "evaluations.csv"))
    assert list(rows[0]) == ["algo", "task", "mode", "seed", "step", "frame", "return", "beta0", "precision"]
    assert len(rows) == 3 * 4 + 3 * 8
    assert {"algo": "curl", "task": TASK, "mode": "training", "seed": "2", "step": "500", "frame": "4000",
            "return": "200", "beta0": "", "precision": "fp32"} in rows
    assert os.path.getsize(os.path.join(out, "curves.png")) > 5000
    assert not os.path.exists(os.path.join(out, "beta0.png"))


def test_aggregates_iqm_from_five_seeds_and_comparisons_within_a_task(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed, ret in zip((1, 2, 3, 4, 5), (100, 200, 300, 400, 1000)):
        make_run(root, "curl", seed, curve(0, 0, ret))
    for seed, ret in zip((1, 2, 3, 4, 5), (400, 500, 600, 700, 800)):
        make_run(root, "im-curl", seed, curve(0, 0, ret))
    write_report(root, out, paper_results=paper_csv, reps=200)
    agg = {(r["fraction"], r["metric"], r["label"]): r for r in read_csv(os.path.join(out, "aggregates.csv"))}
    # IQM of 0.1, 0.2, 0.3, 0.4, 1.0: the middle three, (0.2 + 0.3 + 0.4) / 3.
    iqm = agg["1.0", "IQM", "curl"]
    assert float(iqm["point"]) == pytest.approx(0.3)
    assert float(iqm["ci_low"]) <= 0.3 <= float(iqm["ci_high"]) and iqm["runs"] == "5"
    assert float(agg["1.0", "IQM", "im-curl"]["point"]) == pytest.approx(0.6)
    assert not any(metric != "IQM" for _, metric, _ in agg)  # no cross-task comparisons
    # im-curl against curl on the task: 19.5 of 25 pairs (400 ties 400), Mann-Whitney two-sided.
    pairs = {(r["x"], r["y"], r["fraction"]): r for r in read_csv(os.path.join(out, "comparisons.csv"))}
    pair = pairs["im-curl", "curl", "1.0"]
    assert float(pair["p_x_beats_y"]) == pytest.approx(19.5 / 25)
    assert (pair["n_x"], pair["n_y"], pair["exact"]) == ("5", "5", "1")
    assert 0.05 < float(pair["p_value"]) < 0.2  # exactness is tests/test_stats.py's
    # Identical scores at 0.2T: no improvement either way, p = 1.
    assert (float(pairs["im-curl", "curl", "0.2"]["p_x_beats_y"]), float(pairs["im-curl", "curl", "0.2"]["p_value"])) \
        == (0.5, 1.0)
    md = open(os.path.join(out, "report.md")).read()
    assert "| `training` | `cartpole_swingup_sparse` | 1.0T | im-curl | curl | 5, 5 | +200.0 | 0.78 | 0.167 |" in md


def test_the_iqm_interval_is_the_same_in_every_report_and_leaves_numpys_generator_alone(tmp_path):
    root = str(tmp_path / "sweep")
    for seed, ret in zip((1, 2, 3, 4, 5), (100, 200, 300, 400, 1000)):
        make_run(root, "curl", seed, curve(0, 0, ret))
    intervals = []
    for k in range(2):
        np.random.seed(k)  # whatever state numpy's global generator is in
        before = np.random.get_state()[1].copy()
        out = str(tmp_path / f"report{k}")
        write_report(root, out, reps=200)
        assert (np.random.get_state()[1] == before).all()
        intervals.append([(r["ci_low"], r["ci_high"]) for r in read_csv(os.path.join(out, "aggregates.csv"))])
    assert intervals[0] and intervals[0] == intervals[1]


def test_four_seeds_give_no_iqm_and_say_why(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed in (1, 2, 3, 4):
        make_run(root, "curl", seed, curve(0, 0, 100 * seed))
    write_report(root, out, paper_results=paper_csv, reps=50)
    assert read_csv(os.path.join(out, "aggregates.csv")) == []
    md = open(os.path.join(out, "report.md")).read()
    assert "training at 1.0T: no IQM or bootstrap interval: curl has 4 seeds on some task, and they need at " \
           "least 5" in md


def test_partial_sweep_is_reported_not_crashed(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, curve(10, 100, 100))
    make_run(root, "curl", 2, curve(20, 200, 200))
    make_run(root, "curl", 3, curve(30, 300, 300)[:3])  # still running: last evaluation at step 500
    make_run(root, "im-curl", 1, curve(0, 400, 400))
    make_run(root, "im-curl", 2, [])  # started, no evaluation yet
    with open(os.path.join(root, TASK, "im-curl", "seed_2", "eval.csv"), "a") as fh:
        fh.write("8000,1000,training,9")  # ... and killed while writing its first row
    # The plan says three seeds each: im-curl seed 3 never started.
    plan = {"sweep": {}, "runs": [{"algo": a, "task": TASK, "seed": s, "beta0": None, "steps": 1000, "frames": 8000,
                                   "dir": f"{TASK}/{a}/seed_{s}"} for a in ("curl", "im-curl") for s in (1, 2, 3)]}
    with open(os.path.join(root, "sweep.json"), "w") as fh:
        json.dump(plan, fh)
    write_report(root, out, paper_results=paper_csv, reps=200)
    t = table(out)
    assert (t["training", "curl", "0.5"]["seeds"], t["training", "curl", "0.5"]["expected_seeds"]) == ("3", "3")
    assert float(t["training", "curl", "0.5"]["mean"]) == 200.0
    assert (t["training", "curl", "1.0"]["seeds"], float(t["training", "curl", "1.0"]["mean"])) == ("2", 150.0)
    assert (t["training", "im-curl", "1.0"]["seeds"], t["training", "im-curl", "1.0"]["expected_seeds"]) == ("1", "3")
    md = open(os.path.join(out, "report.md")).read()
    assert "150.0 ± 70.7 (2/3)" in md and "**400.0** ± – (1/3)" in md
    assert "training / cartpole_swingup_sparse / curl at 1.0T (step 1000): no value for seed(s) 3 " \
           "(not reached: last evaluation at step 500)" in md
    assert "im-curl at 1.0T (step 1000): no value for seed(s) 2 (no evaluation in this mode); " \
           "no run for seed(s) 3" in md
    assert f"{TASK}/im-curl/seed_2: no evaluations yet" in md
    assert f"{TASK}/im-curl/seed_3: planned but not started" in md
    # Two and one seeds: no IQM or bootstrap interval, and the notes say why.
    assert read_csv(os.path.join(out, "aggregates.csv")) == []
    assert "training at 1.0T: no IQM or bootstrap interval: curl has 2 seeds, im-curl has 1 seed on some task" in md


def test_points_are_agent_steps_rounded_up():
    from imssr.report.tables import point_step, value_at

    # The paper's points, whatever the task's action repeat.
    assert [point_step(f, 500_000) for f in (0.2, 0.5, 1.0)] == [100_000, 250_000, 500_000]
    # A point between agent steps is the first step at or after it (0.5 * 125 = 62.5 -> 63),
    # where a run made when budgets counted frames evaluated (frame 500 at action repeat 8).
    assert [point_step(f, 125) for f in (0.2, 0.5, 1.0)] == [25, 63, 125]
    evals = [(25, 1.0), (50, 2.0), (63, 3.0), (125, 4.0)]
    assert [value_at(evals, p) for p in (25, 63, 100, 125)] == [1.0, 3.0, 3.0, 4.0]
    assert value_at(evals[:2], 63) is None  # not reached


def test_paper_budget_has_no_budget_note(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, [("training", s, s / 1000) for s in (100_000, 250_000, 500_000)], steps=500_000)
    make_run(root, "curl", 1, [("training", s, s / 1000) for s in (100_000, 250_000, 500_000)],
             task="finger_spin", steps=500_000)
    write_report(root, out, paper_results=paper_csv, reps=50)
    md = open(os.path.join(out, "report.md")).read()
    assert "the paper's numbers are at T" not in md
    # The same agent steps on both tasks, other frames (action repeat 2 on finger_spin).
    assert "| `finger_spin` | 2 | 100,000 steps (200,000 frames) | 250,000 steps (500,000 frames) | " \
           "500,000 steps (1,000,000 frames) |" in md
    assert f"| `{TASK}` | 8 | 100,000 steps (800,000 frames) |" in md
    t = {(r["task"], r["fraction"]): r for r in read_csv(os.path.join(out, "table.csv"))}
    assert [float(t["finger_spin", f]["mean"]) for f in ("0.2", "0.5", "1.0")] == [100.0, 250.0, 500.0]


def test_missing_paper_results_drops_the_column_with_a_note(tmp_path):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, curve(10, 100, 100))
    write_report(root, out, paper_results=str(tmp_path / "nope.csv"), reps=50)
    md = open(os.path.join(out, "report.md")).read()
    assert "paper 1.0T" not in md and f"paper results not found: {tmp_path / 'nope.csv'} (a CSV file" in md
    assert table(out)["training", "curl", "1.0"]["paper_mean"] == ""


def test_the_published_numbers_ship_with_the_package():
    from imssr.report.tables import PaperNumber, load_paper_results

    paper = load_paper_results()  # the default: the IM-SSR paper's Tables I and II, 5 seeds
    assert paper[(TASK, "training", 0.2, "IM-CURL")] == PaperNumber(318.4, 240.3, 5, "IM-SSR paper, Table I")
    assert paper[("walker_walk", "video_hard", 1.0, "IM-SODA")].mean > 0 and len(paper) == 120
    curl = load_paper_results("curl-dmc100k")
    assert curl == {("cartpole_swingup", "training", 1.0, "CURL"):
                    PaperNumber(582.0, 146.0, 10, "CURL paper, Table 1 (100K step scores)")}
    spec = os.path.join(os.path.dirname(REPO), "shared", "spec", "paper_results.csv")
    if os.path.exists(spec):  # the shipped copy holds the spec's every number
        for row in read_csv(spec):
            key = (row["task"], row["mode"], float(row["frames_fraction"]), row["algorithm"])
            assert (paper[key].mean, paper[key].std) == (float(row["mean"]), float(row["std"])), key


def test_a_difference_from_a_published_number_has_its_interval(tmp_path):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed, ret in zip((1, 2, 3), (349.1, 421.7, 762.9)):
        make_run(root, "curl", seed, curve(0, 0, ret), task="cartpole_swingup")
    write_report(root, out, paper_results="curl-dmc100k", reps=50)
    row = table(out)["training", "curl", "1.0"]
    assert (row["paper_mean"], row["paper_std"], row["paper_seeds"]) == ("582", "146", "10")
    # Welch: 511.2 - 582 = -70.8, standard errors 221.0 / sqrt 3 and 146 / sqrt 10, about 2.2 dof.
    diff, low, high = (float(row[k]) for k in ("paper_diff", "paper_diff_low", "paper_diff_high"))
    assert diff == pytest.approx(511.2333 - 582, abs=1e-3) and low < -500 and high > 400
    md = open(os.path.join(out, "report.md")).read()
    assert "| `training` | `cartpole_swingup` | curl | 1.0T | 511.2 ± 221.0 (3) | 582.0 ± 146.0 (n = 10) | -70.8 [" in md


def test_beta_sweep_report_draws_return_against_beta(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed in (1, 2):
        make_run(root, "curl", seed, curve(0, 0, 100 * seed))
        make_run(root, "im-curl", seed, curve(0, 0, 300 + seed), beta0=0.01)
        make_run(root, "im-curl", seed, curve(0, 0, 500 + seed), beta0=0.1)
    written = dict((os.path.basename(p), d) for p, d in write_report(root, out, paper_results=paper_csv, reps=50))
    assert "beta0.png" in written and os.path.getsize(os.path.join(out, "beta0.png")) > 5000
    t = table(out)
    assert float(t["training", "im-curl beta0=0.01", "1.0"]["mean"]) == 301.5
    assert float(t["training", "im-curl beta0=0.1", "1.0"]["beta0"]) == 0.1
    assert t["training", "im-curl beta0=0.1", "1.0"]["best"] == "1"
    # A beta sweep's variants are not the paper's settings: no paper numbers beside them.
    assert t["training", "im-curl beta0=0.1", "1.0"]["paper_mean"] == ""
    md = open(os.path.join(out, "report.md")).read()
    assert "## Beta_0 sensitivity" in md
    pairs = {(r["x"], r["y"], r["fraction"]): r for r in read_csv(os.path.join(out, "comparisons.csv"))}
    assert float(pairs["im-curl beta0=0.01", "curl", "1.0"]["p_x_beats_y"]) == 1.0
    assert {r["beta0"] for r in read_csv(os.path.join(out, "evaluations.csv"))} == {"", "0.01", "0.1"}


def test_report_cli(tmp_path, paper_csv):
    root = str(tmp_path / "sweep")
    make_run(root, "curl", 1, curve(10, 100, 100))
    proc = subprocess.run([sys.executable, "-m", "imssr", "report", root, "--paper-results", paper_csv,
                           "--reps", "50"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert os.path.exists(os.path.join(root, "report", "report.md")) and "report.md" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "imssr", "report", str(tmp_path / "none")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == f"imssr: error: sweep directory not found: {tmp_path / 'none'}"


def test_runs_the_sweep_lists_as_failed_are_reported_as_failed(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, curve(10, 100, 100))
    make_run(root, "curl", 2, curve(20, 200, 200))
    make_run(root, "curl", 3, curve(30, 300, 300)[:2])  # diverged after its evaluation at step 300
    make_run(root, "im-curl", 1, curve(0, 400, 400))
    plan = {"sweep": {}, "runs": [{"algo": a, "task": TASK, "seed": s, "beta0": None, "steps": 1000, "frames": 8000,
                                   "dir": f"{TASK}/{a}/seed_{s}"} for a in ("curl", "im-curl") for s in (1, 2, 3)]}
    with open(os.path.join(root, "sweep.json"), "w") as fh:
        json.dump(plan, fh)
    def run(algo, seed, state, *errors):
        return RunStatus(Run(algo, TASK, seed, None, os.path.join(root, TASK, algo, f"seed_{seed}")), 1000, 8000,
                         state, errors=list(errors))

    SweepDir(root).write_status([
        run("curl", 3, "failed", *["imssr: error: diverged at agent step 412: critic loss nan"] * 2),
        run("im-curl", 2, "failed",  # failed before writing anything
            "imssr: error: device 'cuda:99' requested but CUDA is not available; use --device cpu"),
        run("curl", 1, "done"), run("im-curl", 3, "queued")], started=0.0, retries=1)
    write_report(root, out, paper_results=paper_csv, reps=200)
    t = table(out)
    cell = t["training", "curl", "1.0"]
    assert (cell["seeds"], cell["expected_seeds"], cell["failed_seeds"]) == ("2", "3", "1")
    assert t["training", "curl", "0.2"]["failed_seeds"] == "0"  # it had a value there
    assert (t["training", "im-curl", "1.0"]["seeds"], t["training", "im-curl", "1.0"]["failed_seeds"]) == ("1", "1")
    md = open(os.path.join(out, "report.md")).read()
    assert "4 runs, 14 evaluations. **2 failed** (see Failed runs)." in md
    assert "150.0 ± 70.7 (2/3, 1 failed)" in md and "| 2/3, 1 failed |" in md
    assert "## Failed runs" in md
    assert f"- `{TASK}/curl/seed_3`: diverged at agent step 412: critic loss nan" in md
    assert f"- `{TASK}/im-curl/seed_2`: device 'cuda:99' requested but CUDA is not available" in md
    assert "curl at 1.0T (step 1000): no value for seed(s) 3 (failed: diverged at agent step 412: critic loss nan)" in md
    assert "seed 2 failed before writing anything" in md and "no run for seed(s) 3" in md
    assert f"{TASK}/im-curl/seed_2: planned but not started" not in md
    # A run finished since (done.json) is no longer failed.
    with open(os.path.join(root, TASK, "curl", "seed_3", "done.json"), "w") as fh:
        json.dump({"steps": 1000}, fh)
    write_report(root, out, paper_results=paper_csv, reps=200)
    assert table(out)["training", "curl", "1.0"]["failed_seeds"] == "0"
    assert "**1 failed**" in open(os.path.join(out, "report.md")).read()


def test_compare_sweeps_table_and_exit_status(tmp_path):
    """scripts/compare_sweeps.py: the reference's spread at every common step, the candidate's
    mean inside or not, exit 1 when any point leaves the spread."""
    compare_sweeps = load_script("scripts/compare_sweeps.py")
    ref, near, far = (str(tmp_path / name) for name in ("ref", "near", "far"))
    for seed, (a, b) in enumerate([(10.0, 100.0), (20.0, 200.0), (30.0, 300.0)], start=1):
        make_run(ref, "im-curl", seed, [("training", 250, a), ("training", 500, b)])
        make_run(near, "im-curl", seed, [("training", 250, a + 1), ("training", 500, b - 50)])
        make_run(far, "im-curl", seed, [("training", 250, a), ("training", 500, b + 150)])
    table, inside = compare_sweeps.compare(ref, near, "fp32", "bf16")
    assert inside
    rows = [line for line in table.splitlines() if line.startswith("| 250") or line.startswith("| 500")]
    assert rows[0] == "| 250 | s1: 10.0, s2: 20.0, s3: 30.0 | 20.0 [10.0, 30.0] | s1: 11.0, s2: 21.0, s3: 31.0 | " \
                      "21.0 | +0.10 | yes |"
    assert rows[1].endswith("| 150.0 | -0.50 | yes |")
    table, inside = compare_sweeps.compare(ref, far, "fp32", "bf16")
    assert not inside and table.splitlines()[-1].endswith("| 350.0 | +1.50 | **no** |")
    assert compare_sweeps.main([ref, far]) == 1 and compare_sweeps.main([ref, near]) == 0
    assert compare_sweeps.main([ref, str(tmp_path / "missing")]) == 2
    # A candidate that lacks a seed at a step, or a reference of one seed, does not pass.
    partial, single = str(tmp_path / "partial"), str(tmp_path / "single")
    for seed in (1, 2, 3):
        make_run(partial, "im-curl", seed, [("training", 250, 10.0 * seed)] + ([("training", 500, 200.0)] if seed < 3 else []))
    make_run(single, "im-curl", 1, [("training", 250, 10.0), ("training", 500, 100.0)])
    table, inside = compare_sweeps.compare(ref, partial, "fp32", "bf16")
    assert not inside and table.splitlines()[-1].endswith("| 200.0 | - | **bf16 lacks seed 3** |")
    table, inside = compare_sweeps.compare(single, near, "fp32", "bf16")
    assert not inside and table.splitlines()[-1].endswith("| **no spread: 1 fp32 seed** |")


def test_bf16_runs_are_rows_of_their_own_beside_fp32(tmp_path, paper_csv):
    """The same algo and seeds at two precisions: two rows, two curves, comparisons within each
    precision and within each algo, each seed's return listed."""
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for precision, offset in (("fp32", 0), ("bf16", 50)):
        for seed, ret in zip((1, 2, 3), (100, 200, 300)):
            make_run(root, "curl", seed, curve(0, 0, ret + offset), precision=precision)
            make_run(root, "im-curl", seed, curve(0, 0, ret + offset + 300), precision=precision)
    write_report(root, out, paper_results=paper_csv, reps=100)
    t = table(out)
    assert float(t["training", "curl", "1.0"]["mean"]) == 200.0
    assert float(t["training", "curl bf16", "1.0"]["mean"]) == 250.0
    assert (t["training", "curl", "1.0"]["seeds"], t["training", "curl bf16", "1.0"]["seeds"]) == ("3", "3")
    assert (t["training", "curl", "1.0"]["precision"], t["training", "curl bf16", "1.0"]["precision"]) == ("fp32", "bf16")
    assert t["training", "curl bf16", "1.0"]["per_seed"] == "1:150.0;2:250.0;3:350.0"
    # The published number is the algo's, beside either precision.
    assert t["training", "curl bf16", "1.0"]["paper_mean"] == "744.2"
    labels = [r["label"] for r in read_csv(os.path.join(out, "table.csv")) if r["fraction"] == "1.0"]
    assert labels == ["curl", "im-curl", "curl bf16", "im-curl bf16"]
    # Comparisons within a precision (IM-X against X) and within an algorithm (bf16 against fp32),
    # never across both.
    pairs = {(r["x"], r["y"]) for r in read_csv(os.path.join(out, "comparisons.csv")) if r["fraction"] == "1.0"}
    assert pairs == {("im-curl", "curl"), ("im-curl bf16", "curl bf16"), ("curl bf16", "curl"),
                     ("im-curl bf16", "im-curl")}
    md = open(os.path.join(out, "report.md")).read()
    assert "| curl bf16 | **0.0** ± 0.0 |  | **0.0** ± 0.0 |  | 250.0 ± 100.0 | 744.2 ± 23.8 | 1: 150.0, 2: 250.0, 3: 350.0 | 3/3 |" in md
    assert "| `training` | `cartpole_swingup_sparse` | 1.0T | curl bf16 | curl | 3, 3 | +50.0 | 0.67 | 0.700 |" in md
    assert {r["precision"] for r in read_csv(os.path.join(out, "evaluations.csv"))} == {"fp32", "bf16"}


def test_bf16_runs_with_fp32_q_heads_are_rows_of_their_own(tmp_path, paper_csv):
    """agent.q_heads_fp32 changes a bf16 run's numbers: its runs are the ``bf16-fp32q`` row, never
    seeds of ``bf16``'s; at fp32 the setting does nothing and the runs stay ``fp32``."""
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed in (1, 2):
        make_run(root, "curl", seed, curve(0, 0, 100 * seed), precision="bf16")
        make_run(root, "curl", seed, curve(0, 0, 100 * seed + 500), precision="bf16", q_heads_fp32=True)
        make_run(root, "curl", seed, curve(0, 0, 100 * seed + 300), precision="fp32", q_heads_fp32=True)
    write_report(root, out, paper_results=paper_csv, reps=50)
    t = table(out)
    assert float(t["training", "curl bf16", "1.0"]["mean"]) == 150.0
    assert float(t["training", "curl bf16-fp32q", "1.0"]["mean"]) == 650.0
    assert float(t["training", "curl", "1.0"]["mean"]) == 450.0
    assert {r["precision"] for r in read_csv(os.path.join(out, "evaluations.csv"))} == {"fp32", "bf16", "bf16-fp32q"}


def test_damaged_sweep_files_are_a_note_not_a_crash(tmp_path, paper_csv):
    """A sweep.json cut short is a note (the seeds each group should have then come from the runs
    found); a damaged sweep_status.json lists no failed run."""
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, curve(0, 0, 100))
    for name in ("sweep.json", "sweep_status.json"):
        with open(os.path.join(root, name), "w") as fh:
            fh.write('{"runs": [{"algo": "curl", "state": "failed"')
    write_report(root, out, paper_results=paper_csv, reps=50)
    md = open(os.path.join(out, "report.md")).read()
    assert f"sweep.json: unreadable (sweep plan {root}/sweep.json is not valid JSON: " in md
    assert "expected seeds come from the runs found" in md
    assert "## Failed runs" not in md and table(out)["training", "curl", "1.0"]["seeds"] == "1"


def test_a_planned_bf16_run_that_has_not_started_counts_in_its_own_row(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, curve(0, 0, 100), precision="bf16")
    plan = {"sweep": {"overrides": ["agent.precision=bf16"]},
            "runs": [{"algo": "curl", "task": TASK, "seed": s, "beta0": None, "steps": 1000, "precision": "bf16",
                      "dir": os.path.join("bf16", TASK, "curl", f"seed_{s}")} for s in (1, 2)]}
    with open(os.path.join(root, "sweep.json"), "w") as fh:
        json.dump(plan, fh)
    write_report(root, out, paper_results=paper_csv, reps=50)
    t = table(out)
    assert (t["training", "curl bf16", "1.0"]["seeds"], t["training", "curl bf16", "1.0"]["expected_seeds"]) == ("1", "2")
    assert ("training", "curl", "1.0") not in t


def test_a_non_finite_return_is_left_out_with_a_note(tmp_path, paper_csv):
    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    for seed in (1, 2, 3, 4, 5):
        make_run(root, "curl", seed, curve(0, 100, 100 * seed))
    make_run(root, "curl", 6, curve(0, float("nan"), float("inf")))
    write_report(root, out, paper_results=paper_csv, reps=50)
    t = table(out)
    assert t["training", "curl", "1.0"]["seeds"] == "5" and float(t["training", "curl", "1.0"]["mean"]) == 300.0
    for name in ("table.csv", "aggregates.csv"):
        text = open(os.path.join(out, name)).read().lower()
        assert "nan" not in text and "inf" not in text, name
    md = open(os.path.join(out, "report.md")).read()
    assert (f"{TASK}/curl/seed_6: 2 evaluation(s) with a non-finite return left out: nan at agent step 500 "
            "(training), inf at agent step 1,000 (training)") in md


class PassCounting(list):
    """A list that counts the passes made over it."""

    passes = 0

    def __iter__(self):
        self.passes += 1
        return super().__iter__()


class ReadCounting(dict):
    """A dict that counts the reads of its keys and values."""

    reads = 0

    def get(self, key, default=None):
        self.reads += 1
        return super().get(key, default)

    def __getitem__(self, key):
        self.reads += 1
        return super().__getitem__(key)

    def __iter__(self):
        self.reads += 1
        return super().__iter__()

    def items(self):
        self.reads += 1
        return super().items()


def test_telling_apart_runs_of_one_seed_reads_each_run_a_fixed_number_of_times():
    """Thousands of runs sharing algo, task and seed (copies of one run, sweeps repeated under one
    root): the settings that set them apart are found in linear work, not by comparing every run
    with every other."""
    from imssr.presets import make_config
    from imssr.report.results import RunResult, set_apart

    flat = make_config("curl", TASK).flat()
    reads = []
    for n in (20, 40):
        runs = [RunResult(Run("curl", TASK, 1, None, f"/sweeps/{i}/{TASK}/curl/seed_1"), 1000, 8,
                          settings=ReadCounting(flat, **{"agent.hidden_dim": 64 + i % 2})) for i in range(n)]
        set_apart(runs, "/sweeps")
        assert {r.label for r in runs} == {"curl [agent.hidden_dim=64]", "curl [agent.hidden_dim=65]"}
        reads.append(sum(r.settings.reads for r in runs))
    assert reads[1] == 2 * reads[0]


def test_runs_of_one_seed_that_differ_in_what_they_kept_are_copies_not_variants():
    """Checkpoint settings (scripts/lease_results.py's runs keep none before their end) change no
    number of a run: two runs of one seed that differ only there are labelled by their folders."""
    from imssr.presets import make_config
    from imssr.report.results import RunResult, set_apart

    flat = make_config("curl", TASK).flat()
    kept = {"train.checkpoint_every_steps": 0, "train.save_buffer": False, "train.keep_checkpoints": 3}
    runs = [RunResult(Run("curl", TASK, 1, None, f"/sweeps/{name}/{TASK}/curl/seed_1"), 1000, 8, settings=settings)
            for name, settings in (("sweep", flat), ("lease", {**flat, **kept}))]
    set_apart(runs, "/sweeps")
    assert [r.label for r in runs] == [f"curl [sweep/{TASK}/curl]", f"curl [lease/{TASK}/curl]"]


def test_a_report_passes_over_the_runs_a_fixed_number_of_times(tmp_path, monkeypatch):
    """Each run its own row (copies of one run of one seed): tables, points and curves take a
    fixed number of passes over the runs, not one per row or curve."""
    import shutil

    from imssr.report import report

    collected = []

    def collect(root):
        results = real_collect(root)
        results.runs = PassCounting(results.runs)
        collected.append(results)
        return results

    real_collect = report.collect
    monkeypatch.setattr(report, "collect", collect)
    for n in (3, 6):
        root = tmp_path / f"copies_{n}"
        first = make_run(str(root / "copy_0"), "curl", 1, curve(10, 100, 100))
        for i in range(1, n):
            shutil.copytree(first, root / f"copy_{i}" / TASK / "curl" / "seed_1")
        write_report(str(root), str(tmp_path / f"report_{n}"), reps=20)
        assert len(table(str(tmp_path / f"report_{n}"))) == 3 * n  # a row of its own per copy
    assert collected[0].runs.passes == collected[1].runs.passes


@pytest.mark.parametrize("step", ["inf", "1e30", "-5", "nan", "2.5"])
def test_an_evaluation_at_no_agent_step_is_left_out_with_a_note(tmp_path, paper_csv, step):
    """A step or frame that is no count (a hand-edited or damaged eval.csv) leaves its row out of
    the report and the export, with a note, instead of an OverflowError or matplotlib's TypeError."""
    from imssr.report.export import export_runs

    root, out = str(tmp_path / "sweep"), str(tmp_path / "report")
    make_run(root, "curl", 1, curve(10, 100, 100))
    run = make_run(root, "curl", 2, curve(20, 200, 200))
    path = os.path.join(run, "eval.csv")
    header, first, second, *rest = open(path).read().splitlines()
    cells = second.split(",")
    for column in ("step", "frame"):
        cells[header.split(",").index(column)] = step
    with open(path, "w") as fh:
        fh.write("\n".join([header, first, ",".join(cells), *rest]) + "\n")
    write_report(root, out, paper_results=paper_csv, reps=20)
    assert float(table(out)["training", "curl", "1.0"]["mean"]) == 150.0
    md = open(os.path.join(out, "report.md")).read()
    assert (f"{TASK}/curl/seed_2: 1 evaluation(s) with a step or frame that is no whole number of agent steps or "
            f"frames left out: step {step}, frame {step}") in md
    assert [e.state for e in export_runs(root, str(tmp_path / "export"))] == ["skipped (new)"] * 2


def test_a_run_whose_config_cannot_be_read_is_named_and_the_others_reported(tmp_path, paper_csv, capsys):
    """A config.json with an unknown key: the report and the export name that run and say why,
    and go on with the others; with no other run, the one-line error names it."""
    from imssr.cli import main
    from imssr.report.export import export_runs

    root = str(tmp_path / "sweep")
    bad = make_run(root, "curl", 1, curve(10, 100, 100))
    cfg = json.load(open(os.path.join(bad, "config.json")))
    cfg["agent"]["nope"] = 1
    with open(os.path.join(bad, "config.json"), "w") as fh:
        json.dump(cfg, fh)
    why = f"{TASK}/curl/seed_1: unreadable config.json (unknown setting 'agent.nope'; agent has: "
    for command in (["report", root], ["export", root, str(tmp_path / "dest")]):
        assert main(command) == 2
        [line] = capsys.readouterr().err.splitlines()
        assert line.startswith(f"imssr: error: no readable runs under {root}: {why}")
    make_run(root, "curl", 2, curve(20, 200, 200))
    write_report(root, str(tmp_path / "report"), paper_results=paper_csv, reps=20)
    assert table(str(tmp_path / "report"))["training", "curl", "1.0"]["seeds"] == "1"
    assert f"- {why}" in open(str(tmp_path / "report" / "report.md")).read()
    states = [e.state for e in export_runs(root, str(tmp_path / "dest"))]
    assert states[0].startswith("skipped (unreadable config.json (unknown setting 'agent.nope'") and \
        states[1:] == ["skipped (new)"]


def test_a_seed_that_diverged_on_its_own_is_reported_as_failed(tmp_path, paper_csv):
    """A seed of `imssr train --seeds` that diverged (its status.json, no sweep around it) is
    failed in the report, as in the export, not "not reached"."""
    from imssr.report.export import export_runs
    from imssr.rundir import DIVERGED, FINISHED, RunDir

    root, out = str(tmp_path / "seeds"), str(tmp_path / "report")
    for seed in (1, 2):
        RunDir(make_run(root, "curl", seed, curve(10 * seed, 100 * seed, 100 * seed))).write_status(FINISHED, 1000)
    diverged = make_run(root, "curl", 3, curve(30, 300, 300)[:2])
    RunDir(diverged).write_status(DIVERGED, 412, "diverged at agent step 412: critic loss nan")
    write_report(root, out, paper_results=paper_csv, reps=20)
    cell = table(out)["training", "curl", "1.0"]
    assert (cell["seeds"], cell["expected_seeds"], cell["failed_seeds"]) == ("2", "3", "1")
    md = open(os.path.join(out, "report.md")).read()
    assert "**1 failed** (see Failed runs)" in md and "(2/3, 1 failed)" in md
    assert f"- `{TASK}/curl/seed_3`: diverged at agent step 412: critic loss nan" in md
    assert "no value for seed(s) 3 (failed: diverged at agent step 412: critic loss nan)" in md
    assert export_runs(root, str(tmp_path / "dest"))[-1].state == "skipped (diverged)"
