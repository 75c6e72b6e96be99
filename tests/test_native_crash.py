"""Native crashes: none from the order in which the GL driver and triton load, and a trace of any
that still happens.

Mesa's GL drivers put Debian's libLLVM-15 in the process's global scope; triton (installed with
PyPI's default torch on Linux, and by the test set-up) carries another LLVM whose symbols bind to
the first one loaded.  Every entry point that renders before it builds an agent (torch's Adam
imports triton) runs here in a process of its own, as a user starts it."""
import os
import platform
import sys
import textwrap

import pytest

from conftest import REPO, TINY, run_command, run_imssr, run_python, tiny_config, train_run
from imssr.crash import CRASH_LOG, describe_exit


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A tiny IM-CURL run with a retained checkpoint at agent step 250."""
    out = tmp_path_factory.mktemp("native") / "run"
    train_run(tiny_config(keep_checkpoints=2), out)
    return out


def env():
    return {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}


def test_the_suite_has_triton_where_pypi_torch_brings_it():
    """PyPI's torch depends on triton on Linux x86-64; the test set-up installs it there too, so
    that the suite loads what a user's torch loads (this file's tests are moot without it)."""
    if sys.platform != "linux" or platform.machine() != "x86_64":
        pytest.skip("PyPI's torch brings triton on Linux x86-64 only")
    import importlib.util

    assert importlib.util.find_spec("triton") is not None, "pip install -c constraints.txt -e '.[test]'"


def test_evaluate_renders_then_loads_the_agent(run):
    proc = run_imssr("evaluate", "--run", str(run), "--episodes", "1", "--modes", "training", env=env())
    assert "training: return" in proc.stdout


def test_analyze_renders_then_loads_the_agent(run, tmp_path):
    run_imssr("analyze", "--run", str(run), "--checkpoint", "250", "--states", "6", "--modes", "training",
              "--reps", "20", "--neighbors", "2", "--top-k", "2", "--out", str(tmp_path / "a"), env=env())
    assert (tmp_path / "a" / "states.csv").exists()


def test_the_console_script_renders_then_loads_the_agent(run):
    """The ``imssr`` command that pip installs (the others run ``python -m imssr``)."""
    script = os.path.join(os.path.dirname(sys.executable), "imssr")
    if not os.path.exists(script):
        pytest.skip("imssr is not installed as a command beside this python")
    run_command(script, "evaluate", "--run", str(run), "--episodes", "1", "--modes", "color_hard", env=env())


def test_the_notebook_helpers_render_then_load_the_agent(run):
    code = f"""
        import gymnasium, imssr
        gymnasium.make("imssr/cartpole_swingup_sparse-v0", mode="color_hard", seed=0).reset(seed=0)
        run = imssr.load_run({str(run)!r})
        obs, _ = run.make_env(mode="color_hard").reset(seed=0)
        print(run.act(obs), run.evaluate(mode="color_hard", episodes=1)["return_mean"])
    """
    run_python("-c", textwrap.dedent(code), env=env())


def test_the_python_api_renders_then_trains_with_env_workers(tmp_path):
    """The README's Python API order (an env first, then a Trainer), with the run's envs in
    worker processes that render as well."""
    overrides = {**TINY, "train.steps": 16, "train.seed_steps": 8, "train.burst_updates": 0,
                 "train.eval_every_steps": 16, "train.eval_episodes": 1, "train.env_workers": True,
                 "train.progress": False}
    code = f"""
        import imssr
        imssr.make_env("cartpole_swingup", seed=0).reset()
        from imssr.presets import make_config
        from imssr.training import Trainer
        cfg = make_config("im-curl", "cartpole_swingup")
        for key, value in {overrides!r}.items():
            section, field = key.split(".")
            setattr(getattr(cfg, section), field, value)
        Trainer(cfg, {str(tmp_path / "api")!r}).train()
    """
    run_python("-c", textwrap.dedent(code), env=env(), cwd=REPO)
    assert (tmp_path / "api" / "eval.csv").exists()


def test_a_native_crash_is_told_on_stderr_and_in_the_run_directory(tmp_path):
    """A process that dies of SIGSEGV while it writes a run leaves faulthandler's traceback on
    stderr and in RUN/crash.log; a process that ends normally leaves no crash.log."""
    code = """
        import ctypes, sys
        from imssr.rundir import RunDir
        lock = RunDir(sys.argv[1]).open()
        if sys.argv[2] == "crash":
            ctypes.string_at(0)
        lock.release()
    """
    proc = run_python("-c", textwrap.dedent(code), str(tmp_path / "crashed"), "crash", check=False)
    assert describe_exit(proc.returncode) == "killed by signal 11 (SIGSEGV, a native crash)"
    assert proc.stderr.startswith("Fatal Python error: Segmentation fault")
    log = (tmp_path / "crashed" / CRASH_LOG).read_text()
    assert log.startswith("Fatal Python error: Segmentation fault") and 'File "<string>", line 6' in log
    run_python("-c", textwrap.dedent(code), str(tmp_path / "fine"), "exit")
    assert not (tmp_path / "fine").exists()  # the lock made it, and nothing was left in it


def test_a_failed_command_says_how_it_ended():
    with pytest.raises(AssertionError, match=r"^\S*python\S* -c .* failed, killed by signal 11 \(SIGSEGV, a native "
                                             r"crash\):\n\nFatal Python error: Segmentation fault"):
        run_python("-c", "import faulthandler, ctypes; faulthandler.enable(); ctypes.string_at(0)")
    with pytest.raises(AssertionError, match="failed, exit status 3:"):
        run_python("-c", "raise SystemExit(3)")
