"""IM-SSR intrinsic reward: normalisation, beta schedule, and beta = 0 == baseline."""
import math

import pytest
import torch

from conftest import filled_buffer, tiny_config
from imssr.agents import make_agent
from imssr.errors import ImssrError
from imssr.intrinsic import BetaSchedule, IntrinsicReward, normalize


def test_normalizations():
    x = torch.tensor([1.0, 2.0, 3.0, 6.0])
    z = normalize(x, "zscore")
    assert abs(float(z.mean())) < 1e-6 and float(z.std()) == pytest.approx(1.0, abs=1e-5)
    biased = normalize(x, "zscore", unbiased=False)
    assert float(biased.std(unbiased=False)) == pytest.approx(1.0, abs=1e-5)
    m = normalize(x, "minmax")
    assert float(m.min()) == 0.0 and float(m.max()) == pytest.approx(1.0, abs=1e-6)
    assert float(normalize(x, "mean").mean()) == pytest.approx(1.0, abs=1e-6)
    assert torch.equal(normalize(x, "none"), x)
    # Order is preserved by every method; a constant batch gives a zero bonus.
    for method in ("zscore", "minmax", "mean"):
        assert torch.equal(torch.argsort(normalize(x, method)), torch.argsort(x))
    assert torch.all(normalize(torch.full((5,), 3.0), "zscore") == 0)
    with pytest.raises(ImssrError):
        normalize(x, "softmax")


def test_beta_schedules():
    step = BetaSchedule(0.05, "step", decay=0.8, every_steps=100_000)
    assert step(0) == 0.05 and step(99_999) == 0.05
    assert step(100_000) == pytest.approx(0.04)
    assert step(250_000) == pytest.approx(0.05 * 0.8 ** 2)
    const = BetaSchedule(0.01, "constant")
    assert const(0) == const(10**7) == 0.01
    with pytest.raises(ImssrError):
        BetaSchedule(0.1, "cosine")


def test_intrinsic_reward_scales_normalised_losses():
    cfg = tiny_config("im-curl").intrinsic
    cfg.beta0, cfg.schedule = 0.5, "constant"
    bonus, stats = IntrinsicReward(cfg)(torch.tensor([1.0, 3.0]), beta=cfg.beta0)
    assert bonus.shape == (2, 1)
    # Unbiased std of (1, 3) is sqrt(2): z = -+1/sqrt(2).
    torch.testing.assert_close(bonus.flatten(), 0.5 * torch.tensor([-1.0, 1.0]) / math.sqrt(2))
    assert stats["beta"] == 0.5 and math.isclose(float(stats["r_int_std"]), 1 / math.sqrt(2), rel_tol=1e-5)


def _run(algo, beta0=None, steps=6, seed=0):
    cfg = tiny_config(algo)
    if beta0 is not None:
        cfg.intrinsic.beta0 = beta0
    agent = make_agent((9, 100, 100), 1, cfg.agent, cfg.aux, cfg.intrinsic, seed=seed)
    buf = filled_buffer(seed=1)
    metrics = [agent.update(buf, s) for s in range(steps)]
    return agent, metrics


def _params(agent):
    state = {f"nets.{k}": v for k, v in agent.nets.state_dict().items()}
    state.update({f"aux.{k}": v for k, v in agent.aux.state_dict().items()})
    for i, st in agent.critic_opt.state_dict()["state"].items():
        state.update({f"critic_opt.{i}.{k}": v for k, v in st.items()})
    return state


@pytest.mark.parametrize("base_algo,variant", [
    ("curl", "im-curl"), ("soda", "im-soda"), ("pad", "im-pad"), ("svea", "im-svea"),
    ("curl", "curl+rnd"), ("pad", "pad+re3")])
def test_beta_zero_is_the_baseline_update_for_update(base_algo, variant):
    base, _ = _run(base_algo)
    im0, metrics = _run(variant, beta0=0.0)
    assert "r_int_mean" in metrics[0]  # the intrinsic path really ran
    a, b = _params(base), _params(im0)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_positive_beta_changes_the_critic():
    base, _ = _run("curl", steps=2)
    im, _ = _run("im-curl", beta0=1.0, steps=2)
    diffs = [not torch.equal(p, q) for p, q in zip(base.nets.critic.q.parameters(),
                                                      im.nets.critic.q.parameters())]
    assert any(diffs)
