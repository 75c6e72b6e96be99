"""Every algorithm trains end to end on the real renderer (tiny budget)."""
import math

import pytest

from conftest import tiny_config
from imssr.presets import ALGOS, make_config
from imssr.training import Trainer
from imssr.training.logger import read_csv


def _train(cfg, out, record=None):
    trainer = Trainer(cfg, str(out))
    if record is not None:  # keep every update's metrics
        update = trainer.agent.update
        trainer.agent.update = lambda *a: record.append(update(*a)) or record[-1]
    try:
        trainer.train()
    finally:
        trainer.close()
    return trainer


@pytest.mark.parametrize("algo", list(ALGOS))
def test_every_algorithm_trains_and_evaluates(algo, tmp_path):
    cfg = tiny_config(algo, seed_steps=8, steps=24, eval_every_steps=0)
    metrics = []
    trainer = _train(cfg, tmp_path, metrics)
    assert trainer.agent.updates == len(metrics) == 24 - 8
    assert all(math.isfinite(float(m["critic_loss"])) for m in metrics)
    evals = read_csv(tmp_path / "eval.csv")
    assert len(evals) == 1 and int(evals[0]["step"]) == cfg.train.steps
    spec = ALGOS[algo]
    # The bonus entered the critic's target exactly for algorithms with an intrinsic signal.
    assert all(("bonus_std" in m) == spec.intrinsic_enabled for m in metrics)
    assert all(("aux_loss" in m) for m in metrics[::2]) == (spec.aux != "svea")


@pytest.mark.parametrize("algo", ["soda", "im-soda", "pad", "im-pad", "svea", "im-svea", "soda+rnd"])
def test_dmcgb_presets_train_at_full_size(algo, tmp_path):
    """The paper's networks and batches (11 conv layers, batch 128, SODA batch 256), one update:
    at agent step 8 every piece of it runs (critic, actor, targets and task: every interval of the
    presets divides 8); many updates of every algorithm train above, at tiny sizes."""
    cfg = make_config(algo, "cartpole_swingup_sparse")
    assert cfg.agent.encoder_layers == 11 and cfg.agent.batch_size == 128
    assert all(8 % every == 0 for every in (cfg.agent.critic_update_every, cfg.agent.actor_update_every,
                                             cfg.agent.target_update_every,
                                             cfg.aux.update_every))
    cfg.train.seed_steps = 8
    cfg.train.burst_updates = 0  # the preset's 1000-update burst is budget, not architecture
    cfg.train.steps = 9
    cfg.train.eval_episodes = 1
    cfg.train.tensorboard = cfg.train.progress = False
    cfg.train.replay_capacity = 64
    trainer = _train(cfg, tmp_path)
    assert trainer.agent.updates == 1
