"""The presets train what the authors ran: their settings, budgets in agent steps, their signals.

The committed table ``data/authors_settings.csv`` was written from the authors' code
(duchenzhuang/dmc-disentangle) and Table III, not from the presets; the signal tests compute
IM-CURL's and IM-SODA's bonus independently of the task modules and compare what the critic
update adds to the reward.
"""
import copy
import csv
import math
import os

import pytest
import torch
import torch.nn.functional as F

from conftest import cli_config, filled_buffer, load_script, next_obs_context, tiny_config
from imssr.agents import make_agent
from imssr.augmentations import random_crop
from imssr.config import load_config
from imssr.envs import PAPER_TASKS
from imssr.errors import ImssrError
from imssr.intrinsic import BetaSchedule, IntrinsicReward, normalize
from imssr.presets import ALGOS, BASES, make_config, preset_settings
from imssr.training import Trainer

TABLE = os.path.join(os.path.dirname(__file__), "data", "authors_settings.csv")
ACTION_REPEAT = {"finger_spin": 2, "cartpole_swingup_sparse": 8, "pendulum_swingup": 8}  # Table III; else 4


def _authors_rows():
    with open(TABLE) as fh:
        return list(csv.DictReader(fh))


def _parse(text, like):
    if isinstance(like, bool):
        return text == "true"
    return type(like)(float(text)) if isinstance(like, (int, float)) else text


def _get(cfg, dotted):
    section, name = dotted.split(".")
    return getattr(getattr(cfg, section), name)


@pytest.mark.parametrize("algo", [a for a in ALGOS if "+" not in a])
@pytest.mark.parametrize("task", PAPER_TASKS)
def test_presets_equal_the_authors_settings(algo, task):
    cfg = make_config(algo, task)
    base = ALGOS[algo].base
    applies = {"*", base} | ({algo} if algo.startswith("im-") else set())
    checked = 0
    for row in _authors_rows():
        if row["base"] in applies:
            expected = _parse(row["value"], _get(cfg, row["field"]))
            assert _get(cfg, row["field"]) == expected, f"{row['field']} ({row['source']})"
            checked += 1
    assert checked >= 30
    assert cfg.env.action_repeat == ACTION_REPEAT.get(task, 4)
    assert cfg.total_steps == 500_000 and cfg.total_frames == 500_000 * cfg.env.action_repeat


def test_every_config_field_has_a_source():
    for algo in ALGOS:
        rows = preset_settings(algo, "walker_walk")
        named = {r.field for r in rows}
        data = make_config(algo, "walker_walk").to_dict()
        fields = {f"{s}.{k}" for s, v in data.items() if isinstance(v, dict) for k in v}
        # What a preset leaves at the dataclass default (e.g. RND's settings in a CURL run)
        # does not act in that algorithm.
        unused = {f for f in fields - named if f.startswith(("intrinsic.", "aux."))}
        assert fields - named - unused == set(), algo
        assert all(r.source for r in rows)


def test_official_curl_network_is_one_switch_away():
    cfg = make_config("curl", "walker_walk", network="official-curl")
    assert (cfg.agent.feature_dim, cfg.agent.projection_tanh, cfg.agent.final_relu) == (50, False, True)
    assert make_config("curl", "walker_walk").agent.final_relu is False
    with pytest.raises(ImssrError, match="unknown network"):
        make_config("curl", "walker_walk", network="resnet")


def test_encoder_has_no_relu_after_its_last_convolution_unless_asked():
    for final in (False, True):
        cfg = tiny_config("curl")
        cfg.agent.final_relu = final
        agent = make_agent((9, 100, 100), 1, cfg.agent, cfg.aux, None, seed=0)
        out = agent.nets.critic.encoder.trunk(torch.as_tensor(filled_buffer().sample(4)["obs"][:, :, :84, :84]))
        # A convolution's output has negative values; a ReLU's has none.
        assert bool((out < 0).any()) is not final


def _same_batch(agent, sample):
    state = agent.gen.get_state()
    batch = agent.to_batch(sample)
    agent.gen.set_state(state)
    return batch


def _critic_loss(agent, batch, step=0):
    return agent.critic_objective(batch, agent.beta(step))[1]["critic_loss"]


@torch.no_grad()
def _curl_bonus(agent, batch, beta):
    """Row-wise InfoNCE of (online z of crop c of o', target z of the same crop c), z-scored
    with the unbiased std: the authors' compute_intri_reward, written from its description."""
    n = agent.nets
    z = n.critic.encoder(batch.next_obs)
    k = n.critic_target.encoder(batch.next_obs)
    logits = z @ agent.aux.W @ k.T
    loss = torch.logsumexp(logits, dim=1) - logits.diagonal()
    return beta * (loss - loss.mean()) / loss.std()


@torch.no_grad()
def _soda_bonus(agent, batch, beta, generator):
    """The authors' SODA.intrinsic_reward: online predictor on the clean crop of o', target on its
    overlay, sum over dimensions, log1p, z-score with std + 1e-5."""
    soda = agent.aux
    clean = batch.next_obs
    overlaid = soda.overlay(clean, generator)
    h = soda.predictor(soda.projection(agent.nets.critic.encoder.trunk(clean)))
    t = soda.target_projection(soda.target_trunk(overlaid))
    r = torch.log1p((F.normalize(h, dim=1) - F.normalize(t, dim=1)).pow(2).sum(dim=1))
    return beta * (r - r.mean()) / (r.std() + 1e-5)


@pytest.mark.parametrize("algo", ["im-curl", "im-soda"])
def test_the_bonus_added_to_the_reward_is_the_authors_signal(algo):
    """The IM- update equals the base's update on rewards r + beta * (independent bonus)."""
    beta = 0.3
    cfg = tiny_config(algo)
    cfg.intrinsic.beta0, cfg.intrinsic.schedule = beta, "constant"
    base_cfg = tiny_config(ALGOS[algo].base)
    im = make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=0)
    base = make_agent((9, 100, 100), 2, base_cfg.agent, base_cfg.aux, None, seed=0)
    sample = filled_buffer(action_dim=2).sample(8)
    batch = _same_batch(im, sample)
    if algo == "im-curl":
        bonus = _curl_bonus(im, batch, beta)
    else:
        bonus = _soda_bonus(im, batch, beta, copy.deepcopy(im.intrinsic_gen))
    assert float(bonus.std()) > 0.1  # a real spread, not a degenerate batch
    base_batch = _same_batch(base, sample)
    plain = _critic_loss(copy.deepcopy(base), base_batch)
    base_batch.reward = base_batch.reward + bonus.unsqueeze(-1)
    # The critic's loss is a function of the Bellman target, so of the reward it regresses to.
    expected = _critic_loss(base, base_batch)
    got = _critic_loss(im, batch)
    assert abs(float(expected - plain)) > 1e-3  # the bonus moves the loss measurably
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-7)


def test_the_training_forms_remain_as_options():
    cfg = tiny_config("im-soda")
    agent = make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, cfg.intrinsic, seed=0)
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))

    ctx = next_obs_context(agent, batch)
    ctx.form, ctx.generator = "training", torch.Generator().manual_seed(0)
    training = agent.aux.intrinsic_loss(ctx)
    aug = agent.aux.overlay(batch.next_obs, torch.Generator().manual_seed(0))
    torch.testing.assert_close(training, agent.aux.squared_distance(aug, batch.next_obs).mean(dim=1))
    ctx.form, ctx.generator = "authors", torch.Generator().manual_seed(0)
    assert not torch.allclose(agent.aux.intrinsic_loss(ctx), training)


def test_soda_crops_its_two_branches_independently():
    cfg = tiny_config("soda")
    agent = make_agent((9, 100, 100), 2, cfg.agent, cfg.aux, None, seed=0)
    soda = agent.aux
    batch = agent.to_batch(filled_buffer(action_dim=2).sample(8))
    gen = batch.generator
    state = gen.get_state()
    got = soda.per_sample_loss(batch)
    gen.set_state(state)
    independent = random_crop(batch.raw_obs, cfg.agent.crop_size, gen)
    expected = soda.squared_distance(soda.overlay(independent, gen), batch.obs).mean(dim=1)
    torch.testing.assert_close(got, expected)
    gen.set_state(state)
    shared = soda.squared_distance(soda.overlay(batch.obs, gen), batch.obs).mean(dim=1)
    assert not torch.allclose(got, shared)


def test_beta_decays_at_each_100k_agent_steps_within_the_budget():
    cfg = make_config("im-curl", "walker_walk")
    i = cfg.intrinsic
    schedule = BetaSchedule(i.beta0, i.schedule, i.decay, i.decay_every_steps)
    values = [schedule(s) for s in range(0, cfg.train.steps, 1000)]
    changes = [s * 1000 for s in range(1, len(values)) if values[s] != values[s - 1]]
    assert changes == [100_000, 200_000, 300_000, 400_000]
    assert schedule(cfg.train.steps - 1) == pytest.approx(i.beta0 * 0.8 ** 4)


def test_burst_happens_once_when_the_seed_phase_ends(tmp_path):
    cfg = tiny_config("curl", steps=125, seed_steps=40, eval_every_steps=0, checkpoint_every_steps=125)
    cfg.train.burst_updates = 7
    cfg.train.save_buffer = False
    t = Trainer(cfg, str(tmp_path))
    try:
        t.train()
    finally:
        t.close()
    # 7 updates at step 40, then one at each of steps 41..124.
    assert t.agent.updates == 7 + 84
    # A resume without a buffer refills it with random actions: no second burst.
    cfg2 = load_config(str(tmp_path / "config.json"))
    cfg2.train.steps = 250
    t2 = Trainer(cfg2, str(tmp_path), resume=True)
    try:
        t2.train()
    finally:
        t2.close()
    refill = max(cfg.train.seed_steps, cfg.agent.batch_size)
    assert t2.agent.updates == 7 + 84 + (250 - 125 - refill)


def test_normalize_constant_and_non_finite_batches():
    for method in ("zscore", "minmax"):
        flat = normalize(torch.full((128,), 0.3), method)
        assert torch.equal(flat, torch.zeros(128))
        # Equal up to float rounding is still equal.
        nearly = 0.3 + 1e-9 * torch.randn(128, generator=torch.Generator().manual_seed(0))
        assert torch.equal(normalize(nearly.float(), method), torch.zeros(128))
    spread = normalize(torch.tensor([0.3, 0.31, 0.29, 0.3]))
    assert float(spread.abs().max()) > 0.5
    # A non-finite loss shows in r_int_raw, which the training loop checks with the other
    # metrics (tests/test_run_checks.py): nothing here waits for the device.
    cfg = tiny_config("im-curl").intrinsic
    bonus, stats = IntrinsicReward(cfg)(torch.tensor([0.1, float("nan"), 0.3]), cfg.beta0)
    assert torch.isnan(stats["r_int_raw"]) and torch.isnan(bonus).all()
    _, stats = IntrinsicReward(cfg)(torch.tensor([0.1, float("inf"), 0.3]), cfg.beta0)
    assert not torch.isfinite(stats["r_int_raw"])


def test_cli_budget_in_steps_or_frames(tmp_path):
    def cfg(*extra):
        return cli_config("--algo", "im-curl", "--task", "cartpole_swingup_sparse", "--out", str(tmp_path), *extra)

    assert cfg("--steps", "3000").train.steps == 3000
    assert cfg("--frames", "24001").train.steps == 3001  # rounded up at action repeat 8
    assert cfg().budget_text() == "500,000 agent steps = 4,000,000 frames at action repeat 8"
    with pytest.raises(ImssrError, match="not both"):
        cfg("--steps", "10", "--frames", "80")


def test_every_base_has_a_preset_on_every_paper_task():
    for base in BASES:
        for task in PAPER_TASKS:
            make_config(base, task).validate()
            make_config(f"im-{base}", task).validate()
            assert not math.isnan(make_config(f"im-{base}", task).intrinsic.beta0)


def test_docs_provenance_table_is_in_sync():
    root = os.path.join(os.path.dirname(__file__), "..")
    provenance = load_script("scripts/provenance.py")
    with open(os.path.join(root, "docs", "provenance.md")) as fh:
        assert fh.read() == provenance.provenance_markdown(), \
            "docs/provenance.md is stale: regenerate it with python scripts/provenance.py > docs/provenance.md"
