"""SIGTERM / SIGINT on `imssr train`: real signals on real processes; the stopped run resumes to
exactly the uninterrupted one (on CPU), and the sweep resumes such runs instead of failing them."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import threading

import pytest
import torch

from conftest import tiny_overrides, without_timing
from imssr.cli import main
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import load_checkpoint
from imssr.training.logger import read_csv
from imssr.errors import INTERRUPTED_EXIT
from imssr.sweep.grid import SweepConfig
from imssr.sweep.runner import execute_runs
from imssr.sweep.launchers import LocalLauncher
from imssr.sweep.sweep import _run_sweep, plan_runs, settle
from imssr.rundir.lock import LOCK_FILE

# Tiny curl on cartpole: 2 episodes of 125 agent steps, updates from agent step 100, no
# periodic checkpoint before the end (the stop writes the only one).
TRAIN = ["train", "--algo", "curl", "--task", "cartpole_swingup_sparse", "--steps", "250", "--no-progress",
         "--seed", "3", *[a for kv in (
             *tiny_overrides(), "train.replay_capacity=2000", "train.seed_steps=100",
             "train.burst_updates=0", "train.eval_every_steps=250", "train.eval_episodes=1",
             "train.checkpoint_every_steps=0", "train.tensorboard=false", "train.torch_threads=1")
             for a in ("--set", kv)]]
STOPPED = re.compile(r"imssr: stopped at agent step (\d+) by (SIGTERM|SIGINT); "
                     r"continue with: imssr train --out (\S+) --resume")


def _start(out, *extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    return subprocess.Popen([sys.executable, "-m", "imssr", *TRAIN, *extra, "--out", str(out)], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _after_first_episode(proc, out):
    """Block until the run logged its first episode (agent step 125: the agent is learning)."""
    path = os.path.join(str(out), "train.csv")
    while len(read_csv(path)) < 1:
        assert proc.poll() is None, proc.communicate()
        os.sched_yield()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("reference")
    assert main([*TRAIN, "--out", str(out)]) == 0
    return str(out)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_checkpoints_the_current_step_and_the_resume_is_exact(reference, tmp_path, signum, capsys):
    out = tmp_path / "run"
    proc = _start(out)
    _after_first_episode(proc, out)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == INTERRUPTED_EXIT, err
    lines = [line for line in err.splitlines() if line.strip()]
    match = STOPPED.fullmatch(lines[-1])
    assert match, err
    step = int(match[1])
    assert match[2] == signal.Signals(signum).name and match[3] == str(out)
    assert 125 <= step < 250, err  # after the first episode, before the budget
    state = load_checkpoint(RunDir(str(out)).latest)
    assert state.step == step and state.replay_file
    assert main([*TRAIN, "--out", str(out), "--resume"]) == 0
    assert f"resuming from agent step {step:,}" in capsys.readouterr().out
    for name in ("train.csv", "eval.csv"):
        assert without_timing(read_csv(os.path.join(str(out), name))) == \
            without_timing(read_csv(os.path.join(reference, name))), name
    a = load_checkpoint(RunDir(str(out)).latest).agent["nets"]
    b = load_checkpoint(RunDir(reference).latest).agent["nets"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_a_second_signal_stops_at_once_and_keeps_the_last_checkpoint(tmp_path):
    out = tmp_path / "run"
    proc = _start(out, "--set", "train.checkpoint_every_steps=125")
    while not os.path.exists(RunDir(str(out)).latest):  # the checkpoint of the first episode
        assert proc.poll() is None, proc.communicate()
        os.sched_yield()
    proc.send_signal(signal.SIGTERM)
    assert "stopping after this agent step" in proc.stderr.readline()
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=300)
    # Killed by the second signal, or (if its stop was quicker still) stopped by the first.
    assert proc.returncode in (-signal.SIGTERM, INTERRUPTED_EXIT)
    assert load_checkpoint(RunDir(str(out)).latest).step >= 125


# `imssr train` whose checkpoint write number WRITE (1: the first) gets two signals SIGNAL from the
# process itself in the middle of torch.save: the stop request, then the second signal.  Where
# an outside Ctrl-C lands is chance; these land inside the write every time.
SIGNALS_IN_A_WRITE = """
import os, signal, sys
import imssr.rundir.checkpoint as checkpoint
from imssr.cli import main

WRITE, SIGNAL = int(sys.argv[1]), getattr(signal, sys.argv[2])

class SignalledWriter(checkpoint.HashingWriter):
    writes = 0

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        SignalledWriter.writes += 1
        self.written = 0

    def write(self, data):
        n = super().write(data)
        self.written += len(data)
        if SignalledWriter.writes == WRITE and self.written > 4096:
            SignalledWriter.writes += 1  # once
            os.kill(os.getpid(), SIGNAL)
            os.kill(os.getpid(), SIGNAL)
        return n

checkpoint.HashingWriter = SignalledWriter
sys.exit(main(sys.argv[3:]))
"""


@pytest.mark.parametrize("write", [1, 2])
def test_a_second_signal_during_a_checkpoint_write_exits_130_in_one_line(tmp_path, write):
    """Write 1 is the run's first checkpoint (agent step 125): nothing to resume, and the line
    says so; write 2 (agent step 250) leaves the checkpoint of step 125 whole."""
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    args = [*TRAIN, "--steps", "300", "--set", "train.checkpoint_every_steps=125", "--out", str(out)]
    proc = subprocess.run([sys.executable, "-c", SIGNALS_IN_A_WRITE, str(write), "SIGINT", *args], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == INTERRUPTED_EXIT, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines[-2].startswith("imssr: SIGINT: stopping after this agent step"), proc.stderr
    run = RunDir(str(out))
    if write == 1:
        assert lines[-1] == ("imssr: SIGINT again: stopped at once, before the run's first checkpoint: nothing to "
                             f"resume; choose another --out or remove {out}")
        assert not run.has_checkpoint()
    else:
        assert lines[-1] == ("imssr: SIGINT again: stopped at once, keeping the last checkpoint; continue with: "
                             f"imssr train --out {out} --resume")
        assert load_checkpoint(run.latest).step == 125
    assert run.status() == ("interrupted" if write == 2 else "new")


def test_a_second_signal_ends_a_batch_with_env_workers_at_once_in_one_line(tmp_path):
    """Two seeds in one process, each env in a worker process: the second Ctrl-C (in the seeds'
    checkpoint at agent step 250, after both checkpointed step 125) exits 130 at once with the
    batch's resume command; no worker outlives it (they share its stderr, read to the end).
    SIGTERM takes the same handlers (a run alone:
    test_a_signal_checkpoints_the_current_step_and_the_resume_is_exact)."""
    signum = "SIGINT"  # the name the lines say, and the signal SIGNALS_IN_A_WRITE sends
    out = tmp_path / "batch"
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    seed = TRAIN.index("--seed")
    args = TRAIN[:seed] + TRAIN[seed + 2:] + [
        "--seeds", "1,2", "--steps", "300", "--set", "train.checkpoint_every_steps=125",
        "--set", "train.env_workers=true", "--out", str(out)]
    proc = subprocess.run([sys.executable, "-c", SIGNALS_IN_A_WRITE, "3", signum, *args], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == INTERRUPTED_EXIT, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert lines[-2].startswith(f"imssr: {signum}: stopping after this agent step"), proc.stderr
    assert lines[-1] == (f"imssr: {signum} again: stopped at once, keeping the last checkpoint; continue with: "
                         f"imssr train --seeds 1,2 --out {out} --resume"), proc.stderr
    assert [load_checkpoint(RunDir(str(out / f"seed_{s}")).latest).step for s in (1, 2)] == [125, 125]


def test_the_second_signals_line_says_which_runs_of_a_batch_cannot_resume(tmp_path):
    """Stopped at once during the runs' first checkpoints: the command that continues is named
    only when every run has a checkpoint."""
    from conftest import a_checkpoint
    from imssr.training.stop import StopRequest

    a, b = RunDir(str(tmp_path / "seed_1")), RunDir(str(tmp_path / "seed_2"))
    stop = StopRequest(a, b, resume_command=f"imssr train --seeds 1,2 --out {tmp_path} --resume")
    assert stop._at_once_text() == ("stopped at once, before the runs' first checkpoint: nothing to resume; "
                                    f"choose another --out or remove {a.path}, {b.path}")
    a.save_checkpoint(a_checkpoint(step=5), keep=1)
    assert stop._at_once_text() == (f"stopped at once, during the runs' first checkpoint: {b.path} has none, so "
                                    f"the runs cannot resume together; choose another --out or remove {a.path}, "
                                    f"{b.path}")
    b.save_checkpoint(a_checkpoint(step=5), keep=1)
    assert stop._at_once_text() == ("stopped at once, keeping the last checkpoint; continue with: "
                                    f"imssr train --seeds 1,2 --out {tmp_path} --resume")


def test_after_a_signal_uninstall_gives_the_callers_handlers_back(tmp_path, capfd):
    """`imssr.cli.main` in a process of the caller's (a notebook): once the training is over, the
    caller's handlers are back, not the handler that exits the process at once."""
    from imssr.rundir import RunDir
    from imssr.training.stop import StopRequest

    def mine(signum, frame):
        pass

    previous = signal.signal(signal.SIGTERM, mine)
    # Python's own SIGINT handler, whatever this process inherited (a shell's background job
    # starts with SIGINT ignored).
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        stop = StopRequest(RunDir(str(tmp_path))).install()
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.signal_name == "SIGTERM"
        assert signal.getsignal(signal.SIGTERM) == stop._exit_at_once
        stop.uninstall()
        assert signal.getsignal(signal.SIGTERM) is mine
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGTERM, previous)
        signal.signal(signal.SIGINT, previous_int)
    assert "stopping after this agent step" in capfd.readouterr().err


def test_a_second_signal_that_comes_inside_the_first_ones_handler_stops_at_once(tmp_path, monkeypatch):
    """A second signal that arrives while the first one's handler runs, before it gave way to the
    next: Python runs it inside that call, with the first one's handler.  It is the second
    signal, not a first one again (here SIGTERM comes as the first line is written)."""
    from imssr.training import stop as module

    exits, sent, say = [], [], module._say

    def say_then_signal(text):
        say(text)
        if not sent:
            sent.append(signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(module.os, "_exit", exits.append)  # this process lives on
    monkeypatch.setattr(module, "_say", say_then_signal)
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    stop = module.StopRequest(RunDir(str(tmp_path))).install()
    try:
        os.kill(os.getpid(), signal.SIGINT)
    finally:
        stop.uninstall()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    assert stop.signal_name == "SIGINT" and exits == [INTERRUPTED_EXIT]


def test_signal_handlers_survive_a_closed_stderr(tmp_path, monkeypatch):
    """stderr a closed pipe: the handlers' lines are lost, the stop and the exit still happen."""
    from imssr.rundir import RunDir
    from imssr.training import stop as loop

    def broken(fd, data):
        raise BrokenPipeError(32, "Broken pipe")

    exits = []
    monkeypatch.setattr(loop.os, "write", broken)
    monkeypatch.setattr(loop.os, "_exit", exits.append)
    monkeypatch.setattr(loop.signal, "signal", lambda *args: None)  # this process keeps its handlers
    stop = loop.StopRequest(RunDir(str(tmp_path)))
    stop._handle(signal.SIGTERM, None)
    assert stop.signal_name == "SIGTERM"
    stop._exit_at_once(signal.SIGTERM, None)
    assert exits == [INTERRUPTED_EXIT]


# `imssr train` that sends itself SIGTERM at the agent's update number UPDATE (the real handler
# takes it, wherever the burst is).
SIGTERM_AT_AN_UPDATE = """
import os, signal, sys
from imssr.agents.sac import SACAgent
from imssr.cli import main

UPDATE, update = int(sys.argv[1]), SACAgent.update

def signalled(self, replay, step):
    if self.updates == UPDATE:
        os.kill(os.getpid(), signal.SIGTERM)
    return update(self, replay, step)

SACAgent.update = signalled
sys.exit(main(sys.argv[2:]))
"""


def test_sigterm_inside_the_burst_of_updates_stops_there(tmp_path):
    """The burst of 400 updates at agent step 100 stops at its update 11 (the stop is checked
    before each update), not at its end; that such a checkpoint resumes exactly is
    tests/test_checkpoint.py's."""
    out = tmp_path / "run"
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    args = [*TRAIN, "--set", "train.burst_updates=400", "--out", str(out)]
    proc = subprocess.run([sys.executable, "-c", SIGTERM_AT_AN_UPDATE, "10", *args], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == INTERRUPTED_EXIT, proc.stderr
    last = [line for line in proc.stderr.splitlines() if line.strip()][-1]
    assert last == f"imssr: stopped at agent step 100 by SIGTERM; continue with: imssr train --out {out} --resume"
    state = load_checkpoint(RunDir(str(out)).latest)
    assert state.agent["updates"] == 11 and state.burst_state["updates_done"] == 11


AGAIN = re.compile(r"imssr: (SIGTERM|SIGINT) again: stopped at once, keeping the last checkpoint; "
                   r"continue with: imssr train --out (\S+) --resume")


def test_a_burst_of_ctrl_c_ends_in_one_line_and_130(tmp_path):
    """Many SIGINTs at once, wherever they land (an update, a checkpoint write, the exit): status
    130, one closing line, no traceback, a whole checkpoint."""
    out = tmp_path / "run"
    proc = _start(out, "--set", "train.checkpoint_every_steps=125")
    _after_first_episode(proc, out)
    while not os.path.exists(RunDir(str(out)).latest):  # the checkpoint of the first episode
        assert proc.poll() is None, proc.communicate()
        os.sched_yield()
    for _ in range(20):
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == INTERRUPTED_EXIT, err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    last = [line for line in err.splitlines() if line.strip()][-1]
    assert STOPPED.fullmatch(last) or AGAIN.fullmatch(last), err
    assert load_checkpoint(RunDir(str(out)).latest).step >= 125


def _sweep_run(tmp_path, *overrides):
    """A one-run sweep of the tiny training above: (config, its RunStatus)."""
    sets = [TRAIN[i + 1] for i, a in enumerate(TRAIN) if a == "--set"]
    cfg = SweepConfig(root=str(tmp_path / "sweep"), algos=["curl"], tasks=["cartpole_swingup_sparse"],
                      seeds=[3], steps=250, overrides=sets + list(overrides), retries=0)
    return cfg, plan_runs(cfg)[0]


def test_the_sweep_resumes_a_run_stopped_by_a_signal_instead_of_failing_it(tmp_path, reference):
    cfg, st = _sweep_run(tmp_path)
    run_dir = st.run.dir
    RunDir(run_dir).write_config(st.config)  # as the sweep does before the first attempt
    results = []
    worker = threading.Thread(target=lambda: results.append(execute_runs([run_dir], st.steps, 1)[0]))
    worker.start()
    while len(read_csv(os.path.join(run_dir, "train.csv"))) < 1:  # the training subprocess learns
        assert worker.is_alive()
        os.sched_yield()
    pid = int(open(os.path.join(run_dir, LOCK_FILE)).read().split()[0])
    os.kill(pid, signal.SIGTERM)  # as a scheduler preempting the job would
    worker.join()
    result = results[0]
    assert result["interrupted"] and not result["ok"] and result["returncode"] == INTERRUPTED_EXIT
    assert STOPPED.fullmatch(result["error"]), result["error"]
    assert RunDir(run_dir).status() == "interrupted"
    line = settle(st, result, cfg.retries)  # retries=0: a failure would end the run here
    assert st.state == "queued" and st.action == "resume" and st.errors == [] and st.interruptions == 1, line
    assert line.startswith(f"resume  {st.run.name}: interrupted (imssr: stopped at agent step")
    assert plan_runs(cfg)[0].action == "resume"
    again = execute_runs([run_dir], st.steps, 2)[0]
    assert again["ok"] and again["resumed"] and RunDir(run_dir).is_done(st.steps)
    assert RunDir(run_dir).status() == "finished"
    assert without_timing(read_csv(os.path.join(run_dir, "eval.csv"))) == \
        without_timing(read_csv(os.path.join(reference, "eval.csv")))


def test_an_attempt_waits_for_a_stopping_training_and_resumes_its_checkpoint(tmp_path):
    """A sweep re-run right after its driver was killed: the driver's training, stopped by the
    driver's death, still writes its checkpoint when the new attempt starts.  The attempt waits
    for it and resumes, instead of starting fresh over it (refused: in use, or a run to resume)."""
    cfg, st = _sweep_run(tmp_path)
    run = RunDir(st.run.dir)
    run.write_config(st.config)
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    orphan = subprocess.Popen([sys.executable, "-m", "imssr", "train", "--config", run.config_path, "--out", run.path],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while len(read_csv(os.path.join(run.path, "train.csv"))) < 1:  # learning, no checkpoint yet
            assert orphan.poll() is None
            os.sched_yield()
        assert not run.has_checkpoint()
        orphan.send_signal(signal.SIGTERM)  # PR_SET_PDEATHSIG's signal when its driver dies
        result = execute_runs([run.path], st.steps, 1)[0]
    finally:
        if orphan.poll() is None:
            orphan.kill()
        orphan.wait()
    assert orphan.returncode == INTERRUPTED_EXIT
    assert result["ok"] and result["resumed"], result
    assert run.is_done(st.steps)


def test_sigterm_to_a_ray_sweep_stops_its_trainings_with_checkpoints(tmp_path):
    """`kill` of the sweep (a batch scheduler's stop) on the default launcher: ray.init installs
    a SIGTERM handler of its own (a stack dump and an exit at once), and a Ray task blocked in a
    wait for its training never sees a cancel.  The training must be stopped as a signal to
    `imssr train` stops it (a checkpoint where it is; resuming it is tested above), the status
    file must say interrupted, and the sweep must exit 130."""
    sets = [a for i, a in enumerate(TRAIN) if i and TRAIN[i - 1] == "--set"]
    root = tmp_path / "sweep"
    # A budget far beyond the first episode: a stop that never reaches the training must not
    # pass because the tiny run finished its budget in the meantime.
    cmd = [sys.executable, "-m", "imssr", "sweep", "--no-progress", "--algos", "curl", "--tasks",
           "cartpole_swingup_sparse", "--seeds", "3", "--steps", "5000", "--root", str(root),
           *[a for kv in sets for a in ("--set", kv)]]
    env = dict(os.environ, PYTHONUNBUFFERED="1", MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    run_dir = os.path.join(str(root), "cartpole_swingup_sparse", "curl", "seed_3")
    _after_first_episode(proc, run_dir)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == INTERRUPTED_EXIT, out + err
    assert "SIGTERM received" not in err  # Ray's crash handler did not take the signal
    with open(os.path.join(str(root), "sweep_status.json")) as fh:
        assert [r["state"] for r in json.load(fh)["runs"]] == ["interrupted"]
    assert RunDir(run_dir).status() == "interrupted" and RunDir(run_dir).has_checkpoint()
    with open(os.path.join(run_dir, "sweep.log")) as fh:
        assert STOPPED.search(fh.read())


class _SignalledLauncher(LocalLauncher):
    """The local launcher, with a signal that arrives where Ray's handlers act: during start
    (ray.init's handler exits with the signal's number) or as a second one while stopping."""

    def __init__(self, cfg, at):
        super().__init__(cfg)
        self.at, self.handles = at, []

    def start(self):
        if self.at == "start":
            raise SystemExit(signal.SIGTERM)

    def submit(self, attempts):
        handles = super().submit(attempts)
        self.handles += handles
        if self.at == "stop":
            raise KeyboardInterrupt  # the first signal, with a training in flight
        return handles

    def stop(self, handles):
        raise KeyboardInterrupt  # a second signal while the trainings stop


@pytest.mark.parametrize("at", ["start", "stop"])
def test_a_signal_where_ray_acts_still_leaves_an_interrupted_status(tmp_path, at):
    cfg, st = _sweep_run(tmp_path)
    launcher = _SignalledLauncher(cfg.validate(), at)
    try:
        with pytest.raises(KeyboardInterrupt):
            _run_sweep(cfg, launcher, progress=False, poll_s=0.1)
    finally:
        for handle in launcher.handles:
            handle.stop()
    with open(os.path.join(cfg.root, "sweep_status.json")) as fh:
        assert [r["state"] for r in json.load(fh)["runs"]] == ["queued" if at == "start" else "interrupted"]


def test_ctrl_c_while_the_command_loads_is_one_line(tmp_path):
    # A real KeyboardInterrupt where Ctrl-C lands in the first seconds: while the CLI's modules
    # import.  sitecustomize raises it on the import of imssr.training, which imssr.cli imports.
    (tmp_path / "sitecustomize.py").write_text(
        "import sys\n"
        "class Interrupt:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'imssr.training':\n"
        "            raise KeyboardInterrupt\n"
        "sys.meta_path.insert(0, Interrupt())\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, "-m", "imssr", "tasks"], env=env, capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == INTERRUPTED_EXIT
    assert proc.stderr.strip() == "imssr: interrupted while starting; nothing was run"
    proc = subprocess.run([sys.executable, "-c", "import sys, imssr; print('torch' in sys.modules)"],
                          capture_output=True, text=True, timeout=120)
    assert proc.stdout.strip() == "False"  # what runs before the guard loads no torch


@pytest.mark.parametrize("command, interrupted, says", [
    (["evaluate", "--run", "RUN"], "imssr.training.evaluate.evaluate_run", "imssr evaluate"),
    (["report", "ROOT"], "imssr.report.report.write_report", "imssr report"),
    (["export", "ROOT", "DEST"], "imssr.report.export.export_runs", "imssr export"),
])
def test_ctrl_c_in_a_command_says_what_that_command_left(tmp_path, monkeypatch, capsys, command, interrupted, says):
    import importlib

    import imssr.cli

    def ctrl_c(*args, **kwargs):
        raise KeyboardInterrupt

    module, _, name = interrupted.rpartition(".")
    monkeypatch.setattr(importlib.import_module(module) if module else imssr.cli, name, ctrl_c)
    paths = {"RUN": str(tmp_path / "run"), "ROOT": str(tmp_path), "DEST": str(tmp_path / "dest")}
    assert main([paths.get(a, a) for a in command]) == INTERRUPTED_EXIT
    err = capsys.readouterr().err.strip()
    assert err.startswith("imssr: interrupted; ") and says in err and "\n" not in err
    assert "train --resume" not in err
