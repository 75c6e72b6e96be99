"""Presets follow the paper; overrides and validation give one-line errors."""
import csv
import os

import pytest

from imssr.config import RunConfig, apply_overrides
from imssr.errors import ImssrError
from imssr.envs import PAPER_TASKS
from imssr.presets import ALGOS, PAPER_BETA0, make_config

SPEC = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "spec", "paper_beta0.csv")


def test_curl_preset_matches_table_iii():
    cfg = make_config("curl", "finger_spin")
    a = cfg.agent
    assert (a.encoder_layers, a.encoder_filters, a.discount, a.batch_size) == (4, 32, 0.99, 128)
    assert (a.critic_lr, a.actor_lr, a.alpha_lr, a.alpha_beta1) == (1e-3, 1e-3, 1e-4, 0.5)
    assert (a.actor_update_every, a.critic_update_every, a.crop_size) == (2, 1, 84)
    assert cfg.env.action_repeat == 2 and cfg.env.image_size == 100 and cfg.env.frame_stack == 3
    assert cfg.train.replay_capacity == 100_000 and cfg.train.steps == 500_000
    assert cfg.aux.update_every == 1 and cfg.aux.batch_size == 128
    assert not cfg.intrinsic.enabled


@pytest.mark.skipif(not os.path.exists(SPEC), reason="../shared/spec not beside the repository")
def test_beta0_table_matches_the_paper():
    with open(SPEC) as fh:
        for row in csv.DictReader(fh):
            base = row.pop("algorithm").lower().removeprefix("im-")
            assert {k: float(v) for k, v in row.items()} == PAPER_BETA0[base]


def test_im_presets_use_table_v_and_the_schedule_rule():
    for task in PAPER_TASKS:
        cfg = make_config("im-curl", task)
        assert cfg.intrinsic.enabled and cfg.intrinsic.beta0 == PAPER_BETA0["curl"][task]
        # The authors' CURL scripts decay beta on every task (--in_decay 0.8); the paper's text
        # keeps it fixed on cartpole_swingup_sparse, which the other bases follow.
        assert cfg.intrinsic.schedule == "step"
        expected = "constant" if task == "cartpole_swingup_sparse" else "step"
        assert make_config("im-soda", task).intrinsic.schedule == expected
        assert cfg.intrinsic.decay == 0.8 and cfg.intrinsic.decay_every_steps == 100_000
    assert set(ALGOS) >= {"curl", "im-curl"}


def test_json_round_trip_and_total_steps():
    cfg = make_config("im-curl", "pendulum_swingup")
    again = RunConfig.from_dict(cfg.to_dict())
    assert again == cfg
    assert cfg.total_steps == 500_000 and cfg.total_frames == 4_000_000
    assert cfg.budget_text() == "500,000 agent steps = 4,000,000 frames at action repeat 8"


def test_overrides_and_validation():
    cfg = apply_overrides(make_config("im-curl", "walker_walk"),
                          ["intrinsic.normalization=minmax", "agent.batch_size=64", "train.tensorboard=false"])
    assert cfg.intrinsic.normalization == "minmax" and cfg.agent.batch_size == 64
    assert cfg.train.tensorboard is False
    for bad, msg in [("agent.nope=1", "unknown setting"), ("nope.x=1", "unknown config section"),
                     ("agent.batch_size=1.5", "expects an integer"), ("batch_size=3", "section.field")]:
        with pytest.raises(ImssrError, match=msg):
            apply_overrides(make_config("curl", "walker_walk"), [bad])
    cfg = make_config("curl", "walker_walk")
    cfg.intrinsic.normalization = "softmax"
    with pytest.raises(ImssrError, match="normalization must be one of"):
        cfg.validate()
    with pytest.raises(ImssrError, match="unknown algo"):
        make_config("drq", "walker_walk")


def test_wrong_types_and_inconsistent_settings_are_one_line_errors(tmp_path):
    from imssr.config import load_config

    data = make_config("curl", "walker_walk").to_dict()
    data["train"]["steps"] = "many"
    with pytest.raises(ImssrError, match="train.steps must be a int"):
        RunConfig.from_dict(data).validate()
    with pytest.raises(ImssrError, match="must be an object"):
        RunConfig.from_dict({"env": [1, 2]})
    bad = tmp_path / "list.json"
    bad.write_text("[1, 2]")
    with pytest.raises(ImssrError, match="must be a JSON object"):
        load_config(str(bad))
    for override, msg in [("agent.encoder_layers=60", "leaves no pixels"),
                          ("agent.feature_dim=0", "feature_dim must be >= 1"),
                          ("train.torch_threads=-1", "torch_threads"),
                          ("intrinsic.enabled=true", "choose the algo"),
                          ("train.seed_steps=0", "seed_steps must be >= 1")]:
        with pytest.raises(ImssrError, match=msg):
            apply_overrides(make_config("curl", "walker_walk"), [override]).validate()
