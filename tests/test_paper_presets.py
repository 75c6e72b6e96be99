"""Every paper task trains under the paper's presets (full networks, batch 128), briefly."""
import pytest

from imssr.envs import PAPER_TASKS
from imssr.presets import make_config
from imssr.training import Trainer
from imssr.training.logger import read_csv


@pytest.mark.parametrize("algo", ["curl", "im-curl"])
@pytest.mark.parametrize("task", PAPER_TASKS)
def test_paper_preset_trains(task, algo, tmp_path):
    cfg = make_config(algo, task)
    # Only the budget shrinks: 8 random steps fill the buffer, then 2 full-size updates.
    cfg.train.seed_steps = 8
    cfg.train.steps = 10
    cfg.train.burst_updates = 0  # the preset's 1000-update burst: tested on its own
    cfg.train.eval_episodes = 1
    cfg.train.tensorboard = cfg.train.progress = False
    cfg.train.replay_capacity = 64  # the 100k default would only cost untouched virtual memory
    trainer = Trainer(cfg, str(tmp_path))
    try:
        trainer.train()
    finally:
        trainer.close()
    assert trainer.agent.updates == 2
    rows = read_csv(tmp_path / "eval.csv")
    assert len(rows) == 1 and int(rows[0]["step"]) == 10 and int(rows[0]["frame"]) == 10 * cfg.env.action_repeat
