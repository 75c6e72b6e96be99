"""Shared fixtures: tiny configurations that exercise the real code paths quickly."""
from __future__ import annotations

import csv
import errno
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

import imssr  # noqa: F401 - configures MUJOCO_GL before dm_control loads
from imssr._gl import load_triton_first

# Test modules import dm_control directly (tests/test_env.py at collection), which opens the GL
# driver and its LLVM in the process's global scope; Triton, imported after it (torch.compile,
# Adam through torch._dynamo), would then bind to that LLVM and crash the worker.  imssr's own
# imports of dm_control load Triton first; the tests' direct imports need the same order.
load_triton_first()
from imssr.agents import SACAgent, make_agent
from imssr.batch import NextObsContext
from imssr.presets import make_config
from imssr.training.logger import EVAL_COLUMNS
from imssr.replay import FrameReplayBuffer

# Two torch threads; one per process when pytest-xdist runs the suite on several workers
# (`-n 2`), whose CLI subprocesses inherit OMP_NUM_THREADS (train.torch_threads=0 keeps torch's
# default), so that workers do not contend for the cores.
TORCH_THREADS = 1 if os.environ.get("PYTEST_XDIST_WORKER") else 2
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
torch.set_num_threads(TORCH_THREADS)


# The local sweeps that tests run in this process start Ray as `imssr sweep` does, in Ray's
# single-machine mode (loopback only), which Ray reads when it is first imported: a process that
# imported ray without it is refused (imssr.sweep.launchers.LOCAL_RAY_ENV).
from imssr.sweep.launchers import LOCAL_RAY_ENV  # noqa: E402

os.environ.update(LOCAL_RAY_ENV)

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_script(relpath: str):
    """A script of the repository (``scripts/compare_sweeps.py``, ``bench/gpu.py``) as a module."""
    import importlib.util

    # Registered under a name of its own (dataclasses look their module up while the script runs).
    name = "script_" + "".join(c if c.isalnum() else "_" for c in os.path.splitext(relpath)[0])
    spec = importlib.util.spec_from_file_location(name, os.path.join(REPO, relpath))
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


TINY_NETWORKS = {"agent.hidden_dim": 32, "agent.encoder_filters": 8, "agent.feature_dim": 16,
                 "agent.batch_size": 8, "aux.batch_size": 8}
"""Small MLPs, thin convolutions and batches of 8 (the presets: hidden 1024, 32 filters, 100
features, batch 128, SODA's and PAD's own batch 256)."""

TINY_FRAMES = {"env.image_size": 64, "agent.crop_size": 56, "env.shadow_size": 64}
"""64-px frames cropped to 56 px, with 64-px shadow maps: the real renderer and encoder on about
40% of the pixels of the presets' 100-px frames and 84-px crops, which a tiny run spends most of
its time rendering and convolving."""

TINY = {**TINY_NETWORKS, **TINY_FRAMES}
"""Every setting that makes :func:`tiny_config`'s networks and frames tiny (``section.field``)."""


def tiny_sets(settings: dict | None = None) -> list[str]:
    """:data:`TINY` (or ``settings``) as ``imssr`` command-line overrides: ``--set KEY=VALUE``..."""
    return [a for k, v in (TINY if settings is None else settings).items() for a in ("--set", f"{k}={v}")]


def tiny_overrides(settings: dict | None = None) -> list[str]:
    """:data:`TINY` (or ``settings``) as ``KEY=VALUE`` overrides (a sweep's, the Python API's)."""
    return [f"{k}={v}" for k, v in (TINY if settings is None else settings).items()]


def tiny_config(algo: str = "im-curl", task: str = "cartpole_swingup_sparse", **train):
    """The paper's preset shrunk: :data:`TINY` networks and frames, short budgets."""
    cfg = make_config(algo, task)
    for key, value in TINY.items():
        section, field = key.split(".")
        setattr(getattr(cfg, section), field, value)
    cfg.train.replay_capacity = 5000
    cfg.train.seed_steps = 60
    cfg.train.burst_updates = 0  # DMC-GB presets: 1000
    cfg.train.steps = 250  # 2000 frames at action repeat 8
    cfg.train.eval_every_steps = 125
    cfg.train.eval_episodes = 1
    cfg.train.checkpoint_every_steps = 125
    cfg.train.tensorboard = False
    cfg.train.progress = False
    for k, v in train.items():
        # A misspelt or retired field (e.g. ``frames``) must fail, not be ignored.
        if not hasattr(cfg.train, k):
            raise AttributeError(f"TrainConfig has no field {k!r}")
        setattr(cfg.train, k, v)
    return cfg


class StopAtStep:
    """A stop request as the training loop reads it (``signal_name``, what a
    :class:`~imssr.training.loop.StopRequest` sets on SIGTERM) that arrives at agent step ``step``
    of ``trainer``: as if SIGTERM came during that step."""

    def __init__(self, trainer, step: int):
        self.trainer, self.step = trainer, step

    @property
    def signal_name(self):
        return "SIGTERM" if self.trainer.step >= self.step else None


def a_checkpoint(**fields):
    """A :class:`~imssr.rundir.checkpoint.Checkpoint` with ``fields`` and small stand-ins for the
    rest (no agent, a fresh run's counters): for tests of files and the loop's state."""
    from imssr.rundir.checkpoint import Checkpoint
    from imssr.training.state import RunState

    state = RunState.fresh(0, 0, 0, 0).state_dict()
    base = dict(config=tiny_config("curl").to_dict(), **state, agent={}, env_rng={}, eval_env_rngs={},
                global_rng={})
    return Checkpoint(**{**base, **fields})


def cli_config(*argv: str):
    """The config ``imssr train ARGV`` would train (the CLI's request, planned, not trained)."""
    from imssr.cli import build_parser, train_request
    from imssr.training.entry import plan

    return plan(train_request(build_parser().parse_args(["train", *argv])))[0].config


def cli_status(*argv: str) -> int:
    """The exit status of ``imssr ARGV`` run in this process (the command's own entry point,
    ``imssr.console.main``; argparse's errors leave by :class:`SystemExit`): each start of the
    command in a process of its own costs seconds.  The process's torch threads and environment
    are given back as they were."""
    from imssr.console import main

    threads, environ = torch.get_num_threads(), dict(os.environ)
    try:
        return main(list(argv))
    except SystemExit as exit_:
        return exit_.code
    finally:
        torch.set_num_threads(threads)
        os.environ.clear()
        os.environ.update(environ)


def run_imssr(*args: str, check: bool = True, timeout: float = 600, **kw) -> subprocess.CompletedProcess:
    """``python -m imssr ARGS`` in a process of its own (:func:`run_command`)."""
    return run_python("-m", "imssr", *args, check=check, timeout=timeout, what=f"imssr {' '.join(args)}", **kw)


def run_python(*args: str, **kw) -> subprocess.CompletedProcess:
    """``python ARGS`` (this interpreter) in a process of its own; see :func:`run_command`."""
    return run_command(sys.executable, *args, **kw)


def run_command(*argv: str, check: bool = True, timeout: float = 600, what: str = "",
                **kw) -> subprocess.CompletedProcess:
    """``ARGV`` in a process group of its own, its output captured as text.  With ``check``, a
    failure raises an AssertionError that says how the process ended (its exit status, or the
    signal that killed it: a native crash) and what it printed.  Past ``timeout`` seconds the
    whole group is killed (a shell's children too) and the test fails with what it printed."""
    from imssr.crash import describe_exit

    proc = subprocess.Popen(list(argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kw)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        raise AssertionError(f"{what or ' '.join(argv)} ran past {timeout:.0f} s:\n{out}\n{err}") from None
    if check and proc.returncode != 0:
        raise AssertionError(f"{what or ' '.join(argv)} failed, {describe_exit(proc.returncode)}:\n{out}\n{err}")
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def train_stopped_at(trainer, step: int) -> None:
    """Train ``trainer`` until a stop requested at agent step ``step``: it checkpoints that step
    (the open episode with it, unless an episode ends there with a checkpoint) and stops, as a
    SIGTERM'd process does."""
    from imssr.training.loop import TrainingInterrupted

    trainer.stop = StopAtStep(trainer, step)
    with pytest.raises(TrainingInterrupted, match=f"^stopped at agent step {step} by SIGTERM;"):
        trainer.train()


def train_run(cfg, out, stop_at=None, resume=False, **trainer_kw):
    """Train ``cfg`` into ``out`` (stopped at agent step ``stop_at`` when given, see
    :func:`train_stopped_at`) and release the run directory; returns the closed Trainer."""
    from imssr.training import Trainer

    t = Trainer(cfg, str(out), resume=resume, **trainer_kw)
    try:
        if stop_at is None:
            t.train()
        else:
            train_stopped_at(t, stop_at)
        return t
    finally:
        t.close()


def without_timing(rows, drop=("wall_time", "fps")):
    """Log rows without the columns that measure time, which differ between equal runs."""
    return [{k: v for k, v in r.items() if k not in drop} for r in rows]


def filled_buffer(n_steps: int = 200, action_dim: int = 1, seed: int = 0, episode_len: int = 50,
                  capacity: int = 1000, size: int = 100) -> FrameReplayBuffer:
    """A buffer of random frames in episodes of ``episode_len`` transitions."""
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(capacity, (3, size, size), action_dim, seed=seed)
    for t in range(n_steps):
        if t % episode_len == 0:
            buf.add_first(rng.integers(0, 256, (3, size, size), dtype=np.uint8))
        buf.add(rng.uniform(-1, 1, action_dim), float(rng.normal()), 1.0,
                rng.integers(0, 256, (3, size, size), dtype=np.uint8))
    return buf


def as_single_file_replay(path: str, checksum: bool = True) -> np.ndarray:
    """Rewrite the replay buffer saved as ``path`` in the layout of imssr before frame files: the
    sealed ``.npz`` (no counter, no frame-file list; ``frames_sha256`` when ``checksum``) and one
    ``.frames.npy`` of the ring's first slots.  Returns those frames."""
    import hashlib

    from imssr.integrity import seal_zip
    from imssr.replay.buffer import frames_path, replay_files

    with np.load(path) as data:
        fields = {k: data[k] for k in data.files if k not in ("frame_chunks", "frame_chunk_sha256")}
        capacity, head, size = (int(x) for x in fields["meta"][:3])
        written = int(fields["meta"][4])
        chunks = [(int(a), int(b)) for a, b in data["frame_chunks"]]
    fields["meta"] = fields["meta"][:4]
    extent = capacity if size == capacity else head
    frames = np.zeros((extent, *(int(x) for x in fields["frame_shape"])), np.uint8)
    for (a, b), chunk_file in zip(chunks, replay_files(path)[1:]):
        for k, frame in zip(range(a, b), np.load(chunk_file)):
            if k >= written - size:
                frames[k % capacity] = frame
        os.unlink(chunk_file)
    np.save(frames_path(path), frames)
    if checksum:
        with open(frames_path(path), "rb") as fh:
            fields["frames_sha256"] = np.array(hashlib.sha256(fh.read()).hexdigest())
    with open(path, "wb") as fh:
        np.savez(fh, **fields)
    seal_zip(path)
    return frames


def assert_same_nets(a, b) -> None:
    """Every tensor of two agents' networks is bit-for-bit equal."""
    for (k, v), (_, w) in zip(a.nets.state_dict().items(), b.nets.state_dict().items()):
        assert torch.equal(v, w), k


def assert_same_tensors(a, b, path: str = "") -> int:
    """Two checkpoint states (nested dicts and lists) hold the same keys, bit-for-bit equal
    tensors and equal other values; returns how many tensors were compared."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), path
        return 1
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        return sum(assert_same_tensors(a[k], b[k], f"{path}.{k}") for k in a)
    if isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), path
        return sum(assert_same_tensors(x, y, f"{path}[{i}]") for i, (x, y) in enumerate(zip(a, b)))
    assert a == b, path
    return 0


@pytest.fixture
def tiny_cfg():
    return tiny_config


@pytest.fixture
def tiny_fs(tmp_path):
    """A small tmpfs (needs root): ``mount(size, at=None, inodes=None)`` mounts one of ``size``
    (and at most ``inodes`` files and folders, its root included) at the empty or new folder
    ``at`` (default: a new folder under ``tmp_path``) and returns its mount point."""
    mounted = []

    def mount(size, at=None, inodes=None):
        point = str(at or tmp_path / f"fs{len(mounted)}")
        os.makedirs(point, exist_ok=True)
        options = f"size={size}" + (f",nr_inodes={inodes}" if inodes else "")
        proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", point],
                              capture_output=True, text=True)
        if proc.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {proc.stderr.strip()}")
        mounted.append(point)
        return point

    yield mount
    for point in reversed(mounted):
        subprocess.run(["umount", "-l", point], check=False)


def fill_fs(directory, leave=0):
    """Fill the file system of ``directory`` up to ``leave`` free bytes; return the filler."""
    path = os.path.join(directory, "filler")
    st = os.statvfs(directory)
    with open(path, "wb") as fh:
        try:
            fh.write(bytes(max(0, st.f_bavail * st.f_frsize - leave)))
            fh.flush()
            while not leave:
                fh.write(bytes(1 << 16))
                fh.flush()
        except OSError as exc:
            assert exc.errno == errno.ENOSPC
    return path


# -- run directories as `imssr train` leaves them, for reports ------------------------------

TASK = "cartpole_swingup_sparse"
"""The reports' task: action repeat 8, so agent step s is frame 8 * s."""


def make_run(root, algo, seed, evals, task=TASK, steps=1000, beta0=None, precision="fp32", q_heads_fp32=False):
    """A run directory as `imssr train` leaves it: config.json and eval.csv rows (mode, agent step,
    return); T = ``steps`` agent steps."""
    cfg = make_config(algo, task)
    cfg.train.steps, cfg.train.seed, cfg.agent.precision = steps, seed, precision
    cfg.agent.q_heads_fp32 = q_heads_fp32
    if beta0 is not None:
        cfg.intrinsic.beta0 = beta0
    label = cfg.agent.precision_label
    parts = ([] if label == "fp32" else [label]) + [task, algo] + \
        ([] if beta0 is None else [f"beta0_{beta0!r}"]) + [f"seed_{seed}"]
    run = os.path.join(root, *parts)
    os.makedirs(run)
    with open(os.path.join(run, "config.json"), "w") as fh:
        fh.write(cfg.to_json())
    with open(os.path.join(run, "eval.csv"), "w", newline="") as fh:
        w = csv.DictWriter(fh, EVAL_COLUMNS)
        w.writeheader()
        for mode, step, ret in evals:
            w.writerow({"frame": step * cfg.env.action_repeat, "step": step, "mode": mode, "return_mean": ret, "return_std": 1.0,
                        "episodes": 1, "return_min": ret, "return_max": ret, "wall_time": 0})
    return run


def curve(r02, r05, r10, mode="training"):
    # T = 1000 agent steps.  0.2T = step 200: the evaluation at step 100 is the last at or
    # before it (300 is after); 0.5T = step 500 and 1.0T = step 1000 have an evaluation each.
    return [(mode, 100, r02), (mode, 300, -1.0), (mode, 500, r05), (mode, 1000, r10)]


def small_agent(algo: str, schedule: str = "sequential", precision: str = "fp32", device: str = "cpu",
                agent_fields: dict | None = None, *, seed: int = 0, dtype: torch.dtype | None = None,
                intrinsic=None, **aux) -> SACAgent:
    """The preset of ``algo`` on 60 px frames (9 channels), 4 thin convolutions, batch 8, two
    action dimensions: ``agent_fields`` sets fields of ``cfg.agent``; ``aux`` sets fields of
    ``cfg.aux`` (``own_batch``) or ``cfg.intrinsic`` (``form``); ``intrinsic`` replaces the
    intrinsic config; ``dtype`` casts the networks (float64 for comparisons to rounding)."""
    cfg = tiny_config(algo)
    cfg.agent.update_schedule = schedule
    cfg.agent.precision = precision
    for field, value in (agent_fields or {}).items():
        setattr(cfg.agent, field, value)
    for field, value in aux.items():
        setattr(cfg.intrinsic if field == "form" else cfg.aux, field, value)
    cfg.agent.encoder_layers, cfg.agent.encoder_filters, cfg.agent.crop_size = 4, 8, 52
    cfg.agent.encoder_head_layers = min(cfg.agent.encoder_head_layers, 1)
    cfg.aux.image_pool_size = 8
    agent = make_agent((9, 60, 60), 2, cfg.agent, cfg.aux, intrinsic or cfg.intrinsic, seed=seed, device=device)
    if dtype is not None:
        for module in (agent.nets, agent.aux, agent.signal):
            if module is not None:
                module.to(dtype)
    return agent


def next_obs_context(agent, batch) -> NextObsContext:
    """What an auxiliary task's per-sample loss on o' reads: the batch, its encoding, the
    agent's intrinsic generator, independent crops."""
    return NextObsContext(batch=batch, enc=agent.encode(batch), generator=agent.intrinsic_gen, form="independent")


def image_folder(root, n: int = 5) -> None:
    """``n`` jpg and PNG pictures of several sizes in nested class folders under ``root``, and a
    text file that is no image."""
    from PIL import Image

    rng = np.random.default_rng(0)
    for i in range(n):
        sub = root / f"class_{i % 2}" / "deeper"
        sub.mkdir(parents=True, exist_ok=True)
        size = (40 + 7 * i, 30 + 5 * i)
        arr = rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
        Image.fromarray(arr).save(sub / (f"img{i}.jpg" if i % 2 else f"img{i}.PNG"))
    (root / "notes.txt").write_text("not an image")


def kill_when_file_appears(proc: subprocess.Popen, path: str, timeout: float, what: str, poll: float = 0.5) -> None:
    """SIGKILL ``proc`` as soon as ``path`` exists; fail with ``what`` if it ends or ``timeout``
    seconds pass first.  The process never outlives the call."""
    try:
        deadline = time.time() + timeout
        while not os.path.exists(path):
            assert proc.poll() is None and time.time() < deadline, what
            time.sleep(poll)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()


def cli_help(*argv: str) -> str:
    """What ``imssr ARGV --help`` prints, one option to a line (a wide terminal)."""
    proc = subprocess.run([sys.executable, "-m", "imssr", *argv, "--help"], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "1000"}, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


# -- sweeps ----------------------------------------------------------------------------------

SWEEP_TINY = ["train.seed_steps=60", "train.burst_updates=0", *tiny_overrides(), "train.replay_capacity=3000",
              "train.eval_every_steps=125", "train.eval_episodes=1", "train.checkpoint_every_steps=125",
              "train.tensorboard=false"]
"""The tiny settings of :func:`tiny_config` as the overrides every run of a sweep gets (no
1000-update burst after the seed phase: the presets' DMC-GB burst would dominate a 250-step run)."""


def sweep_status(root) -> dict:
    """``ROOT/sweep_status.json`` as the sweep wrote it: the file's JSON, for tests of what it says."""
    import json

    from imssr.sweep.directory import SweepDir

    with open(SweepDir(str(root)).status_path) as fh:
        return json.load(fh)
