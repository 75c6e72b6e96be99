"""Files someone else wrote (a shared file system): a checkpoint or replay file that would run
code when unpickled is refused in one line, and the code never runs."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch

from conftest import tiny_config
from imssr.cli import main
from imssr.replay import FrameReplayBuffer
from imssr.replay.buffer import ReplayFileError
from imssr.rundir import RunDir
from imssr.rundir.checkpoint import load_checkpoint
from imssr.utils import atomic_write_text


class Evil:
    """Unpickling it runs a shell command that creates ``marker``."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


@pytest.fixture
def run(tmp_path):
    """A run directory with its config (all `imssr evaluate` / `--resume` read before a checkpoint)."""
    path = tmp_path / "run"
    atomic_write_text(str(path / "config.json"), tiny_config("curl").to_json() + "\n")
    return str(path)


def _one_error_line(err):
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("imssr: error: "), err
    return lines[0]


def test_an_evil_checkpoint_is_refused_and_runs_nothing(run, tmp_path, capsys):
    marker = tmp_path / "PWNED"
    evil = str(tmp_path / "evil.pt")
    torch.save({"format_version": 1, "x": Evil(marker)}, evil)
    assert main(["evaluate", "--run", run, "--checkpoint", evil]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line == f"imssr: error: {evil} is not an imssr checkpoint: it contains objects of type os.system"
    assert not marker.exists()
    # The same file as the run's latest.pt: --resume refuses it too.
    os.makedirs(os.path.dirname(RunDir(run).latest))
    os.replace(evil, RunDir(run).latest)
    assert main(["train", "--out", run, "--resume", "--no-progress"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert line.endswith("latest.pt is not an imssr checkpoint: it contains objects of type os.system")
    assert not marker.exists()


def test_a_checkpoint_with_a_class_of_its_own_is_refused(tmp_path):
    path = str(tmp_path / "odd.pt")
    torch.save({"format_version": 1, "x": Evil("/nonexistent/x"), "y": FrameReplayBuffer}, path)
    with pytest.raises(Exception, match=r"it contains objects of type imssr\.replay\.buffer\.FrameReplayBuffer, "
                                        r"os\.system$"):
        load_checkpoint(path)


def test_imssr_checkpoints_hold_only_tensors_and_plain_values(tmp_path):
    """What the trainer saves (numpy RNG states included) needs no allow-listed numpy type."""
    from imssr.utils import rng_states

    run = str(tmp_path / "run")
    RunDir(run).save_checkpoint({"step": 1, "replay_file": None, "global_rng": rng_states()})
    assert torch.serialization.get_unsafe_globals_in_checkpoint(RunDir(run).latest) == []
    assert load_checkpoint(RunDir(run).latest)["global_rng"]["numpy"]["bit_generator"] == "MT19937"


def test_a_replay_file_with_pickled_objects_is_refused(tmp_path):
    marker = tmp_path / "PWNED"
    path = str(tmp_path / "replay.npz")
    np.savez(path, meta=np.array([Evil(marker)], dtype=object), actions=np.zeros((2, 1), np.float32))
    np.save(path + ".frames.npy", np.zeros((2, 3, 8, 8), np.uint8))
    with pytest.raises(ReplayFileError, match=r"^corrupt replay buffer file .*Object arrays cannot be loaded"):
        FrameReplayBuffer(10, (3, 8, 8), 1).load(path)
    assert not marker.exists()
