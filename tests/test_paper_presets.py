"""Every paper task trains under the paper's presets (full networks, batch 128), briefly."""
import pytest

from imssr.envs import PAPER_TASKS
from imssr.presets import make_config
from imssr.training import Trainer
from imssr.training.logger import read_csv


# A base algorithm's preset is its im-X preset with the intrinsic reward off (the last test), and every algorithm trains with and without it in test_algorithms.py: so
# IM-CURL on every paper task, and CURL on one.
CASES = [(task, "im-curl") for task in PAPER_TASKS] + [("cartpole_swingup_sparse", "curl")]


@pytest.mark.parametrize("task,algo", CASES)
def test_paper_preset_trains(task, algo, tmp_path):
    cfg = make_config(algo, task)
    # Only the budget shrinks: 8 random steps fill the buffer, then one full-size update, at agent
    # step 8, where every piece of the update runs (critic, actor, targets, task: each interval
    # divides 8); tests/test_algorithms.py trains many updates of every algorithm at tiny sizes.
    assert all(8 % every == 0 for every in (cfg.agent.critic_update_every, cfg.agent.actor_update_every,
                                             cfg.agent.target_update_every,
                                             cfg.aux.update_every))
    cfg.train.seed_steps = 8
    cfg.train.steps = 9
    cfg.train.burst_updates = 0  # the preset's 1000-update burst: tested on its own
    cfg.train.eval_episodes = 1
    cfg.train.tensorboard = cfg.train.progress = False
    cfg.train.replay_capacity = 64  # the 100k default would only cost untouched virtual memory
    trainer = Trainer(cfg, str(tmp_path))
    try:
        trainer.train()
    finally:
        trainer.close()
    assert trainer.agent.updates == 1
    rows = read_csv(tmp_path / "eval.csv")
    assert len(rows) == 1 and int(rows[0]["step"]) == 9 and int(rows[0]["frame"]) == 9 * cfg.env.action_repeat


@pytest.mark.parametrize("task", PAPER_TASKS)
@pytest.mark.parametrize("base", ["curl", "soda"])
def test_a_base_preset_is_its_im_preset_without_the_intrinsic_reward(task, base):
    """What lets test_paper_preset_trains run CURL on one task only."""
    plain, im = make_config(base, task), make_config(f"im-{base}", task)
    assert not plain.intrinsic.enabled and im.intrinsic.enabled
    for section in ("env", "agent", "aux", "train"):
        assert getattr(plain, section) == getattr(im, section), section
