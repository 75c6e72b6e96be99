"""imssr export: finished runs' configs and CSV logs copied to a committable tree, which
imssr report reads alone (no checkpoint, no replay, no sweep files)."""
import json
import os
import shutil
import subprocess
import sys

import pytest

from conftest import tiny_config, train_run
from imssr.report.export import export_runs
from imssr.report.report import write_report
from imssr.rundir import run_path
from imssr.sweep.grid import load_sweep_file
from imssr.training.logger import read_csv

TASK = "cartpole_swingup_sparse"


def _tiny(algo, seed, precision="fp32"):
    cfg = tiny_config(algo, TASK, seed=seed, steps=80, seed_steps=60, eval_every_steps=80,
                      checkpoint_every_steps=40, torch_threads=1)
    cfg.agent.precision = precision
    return cfg


def _train_finished(cfg, out):
    """Train as ``imssr train`` does, recording how the run ended (status.json)."""
    from imssr.training import Trainer

    trainer = Trainer(cfg, str(out))
    try:
        with trainer.run_dir.recording(lambda: trainer.step):
            trainer.train()
    finally:
        trainer.close()


def test_export_copies_finished_runs_only_and_report_reads_the_copy(tmp_path):
    root, dest = tmp_path / "sweep", tmp_path / "committed"
    finished = {("fp32", "curl", 1), ("fp32", "im-curl", 1), ("bf16", "curl", 1)}
    for precision, algo, seed in sorted(finished):
        _train_finished(_tiny(algo, seed, precision), run_path(str(root / precision), TASK, algo, seed))
    interrupted = run_path(str(root / "fp32"), TASK, "curl", 2)
    train_run(_tiny("curl", 2), interrupted, stop_at=70)

    exported = export_runs(str(root), str(dest))
    states = {os.path.relpath(e.dest, dest): e.state for e in exported}
    assert states == {os.path.join("fp32", TASK, "curl", "seed_1"): "new",
                      os.path.join("fp32", TASK, "im-curl", "seed_1"): "new",
                      os.path.join("bf16", TASK, "curl", "seed_1"): "new",
                      os.path.join("fp32", TASK, "curl", "seed_2"): "skipped (interrupted)"}
    copied = {os.path.relpath(os.path.join(d, f), dest) for d, _, files in os.walk(dest) for f in files}
    expected = {os.path.join(p, TASK, a, f"seed_{s}", name) for p, a, s in finished
                for name in ("config.json", "provenance.json", "eval.csv", "eval_episodes.csv", "train.csv")}
    assert copied == expected  # no checkpoints, replay, tb/, status files, nor the interrupted run
    source = run_path(str(root / "bf16"), TASK, "curl", 1)
    for name in ("config.json", "eval.csv", "train.csv"):
        with open(os.path.join(source, name), "rb") as a, \
                open(os.path.join(dest, "bf16", TASK, "curl", "seed_1", name), "rb") as b:
            assert a.read() == b.read()
    # Exporting again copies nothing.
    assert {e.state for e in export_runs(str(root), str(dest))} == {"unchanged", "skipped (interrupted)"}

    shutil.rmtree(root)  # the report needs only the committed tree
    out = tmp_path / "report"
    write_report(str(dest), str(out), reps=50)
    rows = {(r["label"], r["fraction"]): r for r in read_csv(str(out / "table.csv"))}
    assert {label for label, _ in rows} == {"curl", "im-curl", "curl bf16"}
    for label in ("curl", "im-curl", "curl bf16"):
        assert rows[label, "1.0"]["seeds"] == "1" and rows[label, "1.0"]["step"] == "80"
        assert rows[label, "1.0"]["per_seed"].startswith("1:")
    assert rows["curl bf16", "1.0"]["precision"] == "bf16"
    assert os.path.getsize(out / "curves.png") > 5000


def test_export_refuses_a_destination_inside_the_sweep_and_a_missing_root(tmp_path):
    root = tmp_path / "sweep"
    _train_finished(_tiny("curl", 1), run_path(str(root), TASK, "curl", 1))
    for args, message in (([str(root), str(root / "export")], "is inside the sweep"),
                          ([str(tmp_path / "none"), str(tmp_path / "x")], "sweep directory not found")):
        proc = subprocess.run([sys.executable, "-m", "imssr", "export", *args], capture_output=True, text=True)
        assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1 and message in proc.stderr
    proc = subprocess.run([sys.executable, "-m", "imssr", "export", str(root), str(tmp_path / "x")],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines()[-1] == "imssr: 1 run(s) copied, 0 unchanged, 0 skipped"


def test_a_sweep_file_root_may_start_at_home(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps({"root": "~/imssr-runs/x", "algos": ["curl"], "tasks": [TASK]}))
    assert load_sweep_file(str(path)).root == str(tmp_path / "imssr-runs" / "x")


def test_the_committed_dmc100k_sweeps_differ_only_in_numerics_and_root():
    here = os.path.join(os.path.dirname(__file__), "..", "docs", "results", "dmc100k_cartpole_swingup")
    with open(os.path.join(here, "sweep.json")) as fh:
        fp32 = json.load(fh)
    with open(os.path.join(here, "sweep_bf16.json")) as fh:
        bf16 = json.load(fh)
    assert bf16["set"] == fp32["set"] + ["agent.precision=bf16"]
    assert {k: v for k, v in bf16.items() if k not in ("set", "root")} == \
           {k: v for k, v in fp32.items() if k not in ("set", "root")}
    assert fp32["root"].startswith("~/") and bf16["root"].startswith("~/") and fp32["root"] != bf16["root"]
    with open(os.path.join(here, "sweep_bf16_fp32q.json")) as fh:
        fp32q = json.load(fh)
    assert fp32q["set"] == bf16["set"] + ["agent.q_heads_fp32=true"]
    assert {k: v for k, v in fp32q.items() if k not in ("set", "root")} == \
           {k: v for k, v in bf16.items() if k not in ("set", "root")}
    assert fp32q["root"].startswith("~/") and fp32q["root"] not in (fp32["root"], bf16["root"])
    cfg = load_sweep_file(os.path.join(here, "sweep_bf16_fp32q.json"))
    assert cfg.overrides[-2:] == ["agent.precision=bf16", "agent.q_heads_fp32=true"]
    from imssr.sweep.sweep import plan_runs
    assert {s.config.agent.precision_label for s in plan_runs(cfg)} == {"bf16-fp32q"}


def _finished_store(root, seed=1):
    from imssr.presets import make_config
    from imssr.rundir import RunDir

    run = run_path(str(root), TASK, "curl", seed)
    os.makedirs(run)
    cfg = make_config("curl", TASK)
    cfg.train.seed = seed
    with open(os.path.join(run, "config.json"), "w") as fh:
        fh.write(cfg.to_json())
    for name in ("eval.csv", "train.csv"):
        with open(os.path.join(run, name), "w") as fh:
            fh.write("frame,step,mode,return_mean\n8,1,training,1.0\n")
    RunDir(run).write_status("finished", 1)
    return run


def _keep(repo, root, dest="runs", env=None):
    script = os.path.join(os.path.dirname(__file__), "..", "scripts", "keep_results.py")
    return subprocess.run([sys.executable, script, str(root), dest, "--every", "0", "--wait-start", "0"], cwd=repo,
                          capture_output=True, text=True, env=env, timeout=300)


def _committed(repo):
    return subprocess.run(["git", "-C", str(repo), "log", "--format=%s", "--name-only"], capture_output=True,
                          text=True, check=True).stdout


def test_keep_results_commits_each_finished_run_once_and_stops_with_the_sweep(tmp_path):
    repo, root = tmp_path / "repo", tmp_path / "store"
    _finished_store(root)
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    subprocess.run(["git", "-C", str(repo), "commit", "-q", "--allow-empty", "-m", "start"], check=True)
    (repo / "other.txt").write_text("work in progress\n")
    for _ in range(2):  # no sweep holds the store: one export, then exit
        proc = _keep(repo, root)
        assert proc.returncode == 0, proc.stderr
    log = _committed(repo)
    assert log.count("results: ") == 1 and f"runs/fp32/{TASK}/curl/seed_1/eval.csv" in log
    assert "other.txt" not in log  # only the export is committed


def test_keep_results_commits_later_what_a_failed_commit_left_and_only_its_own_files(tmp_path):
    repo, root = tmp_path / "repo", tmp_path / "store"
    _finished_store(root)
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    subprocess.run(["git", "-C", str(repo), "commit", "-q", "--allow-empty", "-m", "start"], check=True)
    # No git identity at first: the commit fails in one line, the files stay uncommitted.
    env = {k: v for k, v in os.environ.items() if not k.startswith("GIT_")}
    env.update(HOME=str(tmp_path / "home"), GIT_CONFIG_NOSYSTEM="1", GIT_CONFIG_GLOBAL=os.devnull)
    subprocess.run(["git", "-C", str(repo), "config", "user.useConfigOnly", "true"], check=True)
    proc = _keep(repo, root, env=env)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith("keep_results: git commit failed (") and proc.stderr.count("\n") == 1
    assert proc.stderr.strip().endswith("the next export tries again")
    # A draft of the user's in DEST, and a temporary file a killed export left in a run.
    target = repo / "runs" / "fp32" / TASK / "curl" / "seed_1"
    (repo / "runs" / "draft.md").write_text("notes\n")
    (target / ".tmp-0123abcd-eval.csv").write_text("half")
    # Another git holds the index: the same one line, nothing lost.
    (repo / ".git" / "index.lock").write_text("")
    proc = _keep(repo, root)
    assert proc.returncode == 1 and proc.stderr.startswith("keep_results: git add failed (")
    os.unlink(repo / ".git" / "index.lock")
    # The next pass commits what the failed ones left, though the export itself copies nothing.
    proc = _keep(repo, root)
    assert proc.returncode == 0, proc.stderr
    log = _committed(repo)
    assert log.count("results: ") == 1 and f"runs/fp32/{TASK}/curl/seed_1/eval.csv" in log
    assert "draft.md" not in log and ".tmp-" not in log
    assert not (target / ".tmp-0123abcd-eval.csv").exists()  # the export removed its own leftover
    assert (repo / "runs" / "draft.md").exists()


def test_keep_results_refuses_a_dest_outside_a_work_tree(tmp_path):
    outside = tmp_path / "plain"
    outside.mkdir()
    proc = _keep(outside, tmp_path / "store", env={**os.environ, "GIT_CEILING_DIRECTORIES": str(tmp_path)})
    assert proc.returncode == 2 and proc.stderr.startswith("keep_results: error: ") and "not inside a git work tree" \
        in proc.stderr and proc.stderr.count("\n") == 1
    repo = tmp_path / "repo"
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    proc = _keep(repo, tmp_path / "store", dest=str(tmp_path / "elsewhere"))
    assert proc.returncode == 2 and "is outside the git work tree" in proc.stderr


def test_keep_results_refuses_a_dest_that_git_ignores_before_waiting(tmp_path):
    repo = tmp_path / "repo"
    subprocess.run(["git", "init", "-q", str(repo)], check=True)
    (repo / ".gitignore").write_text("runs/\n")
    script = os.path.join(os.path.dirname(__file__), "..", "scripts", "keep_results.py")
    proc = subprocess.run([sys.executable, script, str(tmp_path / "store"), "docs/runs", "--wait-start", "600"],
                          cwd=repo, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.startswith("keep_results: error: git ignores docs/runs here") and proc.stderr.count("\n") == 1


def test_export_refuses_a_log_that_is_a_link_out_of_the_run(tmp_path):
    root = tmp_path / "sweep"
    run = run_path(str(root), TASK, "curl", 1)
    _train_finished(_tiny("curl", 1), run)
    secret = tmp_path / "secret.txt"
    secret.write_text("not a result\n")
    os.unlink(os.path.join(run, "eval_episodes.csv"))
    os.symlink(secret, os.path.join(run, "eval_episodes.csv"))
    proc = subprocess.run([sys.executable, "-m", "imssr", "export", str(root), str(tmp_path / "x")],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == f"imssr: error: {os.path.join(run, 'eval_episodes.csv')} is a symbolic link; " \
                                  "the export copies only a run's own files"
    assert not any("secret" in open(os.path.join(d, f)).read()
                   for d, _, files in os.walk(tmp_path / "x") for f in files)


def test_git_keeps_the_results_trees_and_ignores_the_top_level_runs():
    """scripts/keep_results.py commits an export under docs/results/<name>/runs: git must not
    ignore it, while the top-level runs/ (where the README's commands write) stays ignored."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    if shutil.which("git") is None or not os.path.exists(os.path.join(root, ".git")):
        pytest.skip("not a git checkout")

    def ignored(path):
        return subprocess.run(["git", "check-ignore", "-q", "--no-index", path], cwd=root).returncode == 0

    assert not ignored("docs/results/dmc100k_cartpole_swingup/runs/fp32/cartpole_swingup/curl/seed_1/eval.csv")
    assert not ignored("docs/results/any_sweep/runs/bf16/cartpole_swingup/curl/seed_1/config.json")
    assert ignored("runs/demo/eval.csv")


@pytest.mark.parametrize("field, value", [("env.task", "../../escape"), ("env.task", "/abs/escape"),
                                          ("algo", "..")])
def test_export_never_writes_outside_dest_for_names_read_from_a_run(tmp_path, field, value):
    root, dest = tmp_path / "sweep", tmp_path / "deep" / "dest"
    run = run_path(str(root), TASK, "curl", 1)
    _train_finished(_tiny("curl", 1), run)
    cfg = json.loads(open(os.path.join(run, "config.json")).read())
    section, _, name = field.rpartition(".")
    (cfg[section] if section else cfg)[name] = value
    with open(os.path.join(run, "config.json"), "w") as fh:
        json.dump(cfg, fh)
    before = sorted(str(p) for p in tmp_path.rglob("*"))
    exported = export_runs(str(root), str(dest))
    assert [e.state for e in exported] == [
        f"skipped (its config.json names {'task' if name == 'task' else 'algo'} {value!r}: not a plain name)"]
    assert sorted(str(p) for p in tmp_path.rglob("*")) == before  # nothing written anywhere


def test_runs_that_differ_only_in_a_setting_stay_apart_in_report_and_export(tmp_path):
    """Two sweeps under one root that differ in a --set (same algo, task and seed): the report
    gives each its own row, labelled by the setting, and the export keeps both."""
    root, dest = tmp_path / "sweep", tmp_path / "dest"
    for norm, seed_runs in (("zscore", 2), ("minmax", 2)):
        for seed in range(1, seed_runs + 1):
            cfg = _tiny("im-curl", seed)
            cfg.intrinsic.normalization = norm
            _train_finished(cfg, run_path(str(root / norm), TASK, "im-curl", seed))
    write_report(str(root), str(tmp_path / "report"), reps=20)
    rows = read_csv(str(tmp_path / "report" / "table.csv"))
    labels = sorted({r["label"] for r in rows})
    assert labels == ["im-curl [intrinsic.normalization=minmax]", "im-curl [intrinsic.normalization=zscore]"]
    assert {r["seeds"] for r in rows if r["fraction"] == "1.0"} == {"2"}
    exported = export_runs(str(root), str(dest))
    assert [e.state for e in exported] == ["new"] * 4
    assert len({e.dest for e in exported}) == 4
    assert export_runs(str(root), str(dest)) and all(e.state == "unchanged" for e in export_runs(str(root), str(dest)))
    write_report(str(dest), str(tmp_path / "report2"), reps=20)
    assert sorted({r["label"] for r in read_csv(str(tmp_path / "report2" / "table.csv"))}) == labels


def test_export_cuts_the_absolute_paths_of_a_config_that_the_run_keeps_whole(tmp_path):
    """Data folders given as absolute paths (``aux.image_dir``, ``env.footage_dir``) stay whole in
    the run's own config.json, which a resume and `imssr evaluate` read, and reach the export cut
    to their last part, ``…/imgs``, as provenance.json's command line has them: an export is made
    to be shared, and carries no file of its author's machine."""
    root, dest = tmp_path / "sweep", tmp_path / "dest"
    images, footage = tmp_path / "alice" / "imgs", tmp_path / "alice" / "clips"
    os.makedirs(images)
    os.makedirs(footage)
    cfg = _tiny("curl", 1)
    cfg.aux.image_dir, cfg.env.footage_dir = str(images), str(footage)
    run = run_path(str(root), TASK, "curl", 1)
    _train_finished(cfg, run)
    own = json.load(open(os.path.join(run, "config.json")))
    assert (own["aux"]["image_dir"], own["env"]["footage_dir"]) == (str(images), str(footage))

    [item] = export_runs(str(root), str(dest))
    assert item.state == "new"
    for folder, _, names in os.walk(dest):
        for name in names:
            assert str(tmp_path) not in open(os.path.join(folder, name), encoding="utf-8").read(), name
    shared = json.load(open(os.path.join(item.dest, "config.json")))
    assert (shared["aux"]["image_dir"], shared["env"]["footage_dir"]) == ("…/imgs", "…/clips")
    assert {k: v for k, v in shared.items() if k not in ("aux", "env")} == \
        {k: v for k, v in own.items() if k not in ("aux", "env")}
    assert [e.state for e in export_runs(str(root), str(dest))] == ["unchanged"]
    write_report(str(dest), str(tmp_path / "report"), reps=20)
    assert read_csv(str(tmp_path / "report" / "table.csv"))[0]["label"] == "curl"
