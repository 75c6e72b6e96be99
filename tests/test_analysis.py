"""imssr analyze: recorded physics states, re-rendering, the three measures, the command end to end."""
import csv
import os
import shutil

import numpy as np
import pytest
import torch

from conftest import tiny_config, train_run
from imssr.analysis import adapter, measures
from imssr.analysis.report import spearman_ci
from imssr.analysis.states import candidates
from imssr.cli import main
from imssr.envs import make_env
from imssr.replay import FrameReplayBuffer


def _episode(task="cartpole_swingup", steps=12, seed=3, size=32):
    """A random-action episode: its frames, observations, physics states and a buffer holding them."""
    env = make_env(task, seed=seed, image_size=size)
    rng = np.random.default_rng(seed)
    buf = FrameReplayBuffer(100, (3, size, size), env.action_space.shape[0], physics_dim=env.physics_state_dim)
    obs, info = env.reset()
    frames, observations, states = [info["frame"]], [obs], [env.physics_state().copy()]
    buf.add_first(info["frame"], env.physics_state(), 0)
    for t in range(steps):
        action = rng.uniform(-1, 1, env.action_space.shape)
        obs, reward, _, _, info = env.step(action)
        buf.add(action, reward, 1.0, info["frame"], env.physics_state(), t + 1)
        frames.append(info["frame"]); observations.append(obs); states.append(env.physics_state().copy())
    env.close()
    return frames, observations, np.stack(states), buf


@pytest.mark.parametrize("task", ["cartpole_swingup", "walker_walk"])
def test_rerendering_a_recorded_state_reproduces_its_frame_exactly(task):
    frames, observations, states, _ = _episode(task)
    other = make_env(task, seed=99, image_size=32)  # another env, another seed: only the state matters
    try:
        for frame, state in zip(frames, states):
            assert np.array_equal(other.render_stack(state[None]), frame)
        # A whole stack, including the repeated first frame right after the reset.
        assert np.array_equal(other.render_stack(states[[0, 0, 1]]), observations[1])
        assert np.array_equal(other.render_stack(states[-3:]), observations[-1])
    finally:
        other.close()


def test_test_scene_rerenders_the_same_state_differently_and_reproducibly():
    _, observations, states, _ = _episode()
    a, b = (make_env("cartpole_swingup", seed=5, mode="color_hard", image_size=32) for _ in range(2))
    try:
        x, y = a.render_stack(states[-3:]), b.render_stack(states[-3:])
    finally:
        a.close(); b.close()
    assert np.array_equal(x, y)
    assert not np.array_equal(x, observations[-1])


def test_replay_round_trip_keeps_physics_states_and_agent_steps(tmp_path):
    _, _, states, buf = _episode()
    path = str(tmp_path / "replay.npz")
    buf.save(path)
    other = FrameReplayBuffer(100, buf.frame_shape, buf.action_dim, physics_dim=buf.physics_dim)
    other.load(path)
    n = buf.head
    assert np.array_equal(other.physics[:n], states) and np.array_equal(other.agent_step[:n], np.arange(n))
    assert np.array_equal(other.frames[:n], buf.frames[:n])


def test_a_replay_saved_without_physics_still_loads(tmp_path):
    _, _, _, buf = _episode()
    old = FrameReplayBuffer(100, buf.frame_shape, buf.action_dim)  # as written before physics were recorded
    old.add_first(buf.frames[0])
    for i in range(1, buf.head):
        old.add(buf.actions[i - 1], float(buf.rewards[i - 1]), 1.0, buf.frames[i])
    path = str(tmp_path / "old.npz")
    old.save(path)
    new = FrameReplayBuffer(100, buf.frame_shape, buf.action_dim, physics_dim=buf.physics_dim)
    new.load(path)
    assert np.array_equal(new.frames[:buf.head], buf.frames[:buf.head])
    assert np.isnan(new.physics[:buf.head]).all() and (new.agent_step[:buf.head] == -1).all()
    assert new.num_transitions() == buf.num_transitions()
    assert len(candidates(new)) == 0 and len(candidates(buf)) > 0  # analysis falls back to rollouts


def test_memory_figure_counts_the_physics_states():
    cartpole = FrameReplayBuffer(10, (3, 100, 100), 1, physics_dim=4, warn_memory=False)
    walker = FrameReplayBuffer(10, (3, 100, 100), 6, physics_dim=18, warn_memory=False)
    assert cartpole.bytes_per_slot() == 30_052 and walker.bytes_per_slot() == 30_184
    assert walker.nbytes_expected() == sum(a.nbytes for a in (
        walker.frames, walker.actions, walker.rewards, walker.discounts, walker.step_in_episode,
        walker.physics, walker.agent_step))


def test_novelty_of_a_duplicated_state_is_zero():
    rng = np.random.default_rng(0)
    pool = rng.normal(size=(50, 4))
    pool[7] = pool[3]
    pool[20:22] = pool[10]
    d = measures.knn_distance(pool[[3, 10, 30]], pool, 1, exclude=np.array([3, 10, 30]))
    assert d[0] == 0.0 and d[1] == 0.0 and d[2] > 0
    # k = 3 needs three other copies: the state itself (excluded) and two more give a positive distance.
    assert measures.knn_distance(pool[[10]], pool, 3, exclude=np.array([10]))[0] > 0
    pool[40] = pool[10]
    assert measures.knn_distance(pool[[10]], pool, 3, exclude=np.array([10]))[0] == 0.0
    nan_pool = pool.copy(); nan_pool[7] = np.nan  # an unrecorded state is no neighbour
    assert measures.knn_distance(pool[[3]], nan_pool, 1, exclude=np.array([3]))[0] > 0


def test_a_full_turn_of_an_unlimited_hinge_is_the_same_state():
    env = make_env("cartpole_swingup", seed=0, image_size=32)
    try:
        state = env.physics_state().copy()
        turned = state.copy(); turned[1] += 2 * np.pi  # the pole's hinge (the cart's slider is limited)
        a, b = measures.state_coordinates(env.physics, np.stack([state, turned]))
    finally:
        env.close()
    assert np.allclose(a, b) and len(a) == len(state) + 1


def test_first_visit_is_the_earliest_step_of_a_state_nearby():
    pool = np.array([[0.0], [5.0], [0.1], [5.05]])
    steps = np.array([10, 20, 30, 40])
    first = measures.first_visit(pool[[2, 3]], pool, steps, 0.2, np.array([30, 40]))
    assert list(first) == [10, 20]


def test_spearman_ci_brackets_the_estimate_and_is_seeded():
    rng = np.random.default_rng(1)
    x = rng.normal(size=60)
    y = x + rng.normal(size=60)
    a, b = spearman_ci(x, y, 300, seed=4), spearman_ci(x, y, 300, seed=4)
    assert a == b and a["ci_low"] < a["rho"] < a["ci_high"] and a["rho"] > 0.4
    assert np.isnan(spearman_ci(x, np.ones(60))["rho"])


def test_adapter_gives_the_signal_the_agent_adds_to_its_reward():
    from imssr.training import build_agent

    cfg = tiny_config()
    _, _, _, buf = _episode(steps=20, size=100)
    agent = build_agent(cfg, (9, 100, 100), 1, "cpu")
    sample = buf.gather(buf.sample_indices(cfg.agent.batch_size))
    seen = []

    class Recording(type(agent.intrinsic)):
        """The agent's own IntrinsicReward, keeping the raw signal it is handed."""

        def __call__(self, losses, beta):
            seen.append(losses.detach().clone())
            return super().__call__(losses, beta)

    agent.intrinsic.__class__ = Recording  # a call goes through the class, not the instance
    gen_state, int_state = agent.gen.get_state(), agent.intrinsic_gen.get_state()
    ours = adapter.intrinsic_signal(agent, sample)
    agent.gen.set_state(gen_state); agent.intrinsic_gen.set_state(int_state)
    batch = agent.to_batch(sample)
    agent.critic_objective(batch, agent.beta(1))
    assert torch.equal(ours, seen[0])


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def _snapshot(run):
    return {os.path.relpath(os.path.join(d, f), run): os.stat(os.path.join(d, f)).st_mtime_ns
            for d, _, files in os.walk(run) for f in files}


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny IM-CURL run with two retained checkpoints (agent steps 125 and 250) and its replay."""
    cfg = tiny_config(keep_checkpoints=2)
    run = tmp_path_factory.mktemp("analyze") / "run"
    train_run(cfg, run)
    return cfg, run


def test_analyze_runs_end_to_end_on_a_tiny_run(tiny_run, capsys):
    cfg, run = tiny_run
    before = _snapshot(str(run))
    assert main(["analyze", "--run", str(run), "--states", "12", "--modes", "training,color_hard",
                 "--reps", "50", "--neighbors", "2", "--top-k", "2"]) == 0
    after = _snapshot(str(run))
    assert {k: v for k, v in after.items() if not k.startswith("analysis")} == before  # the run is only read
    out = run / "analysis"
    for name in ("states.csv", "correlations.csv", "analysis.png", "montage.png"):
        assert (out / name).stat().st_size > 0
    rows = _rows(out / "states.csv")
    assert sorted({int(r["checkpoint_step"]) for r in rows}) == [125, 250] and len(rows) == 24
    assert all(float(r["nuisance_training"]) == 0.0 for r in rows)
    assert any(float(r["nuisance_color_hard"]) > 0 for r in rows)
    assert all(int(r["agent_step"]) >= int(r["first_visit_step"]) >= 0 for r in rows)
    assert all(np.isfinite(float(r["signal"])) and float(r["novelty_all"]) >= 0 for r in rows)
    # The early checkpoint's novelty is measured against the states stored by its step only.
    early = [r for r in rows if r["checkpoint_step"] == "125"]
    assert all(r["seen_by_checkpoint"] == str(int(int(r["first_visit_step"]) <= 125)) for r in early)
    text = capsys.readouterr().out
    assert "12 of 12 stacks equal the stored frames" in text
    corr = _rows(out / "correlations.csv")
    assert {c["against"] for c in corr} >= {"novelty", "nuisance_color_hard", "nuisance_mean"}
    assert {c["checkpoint_step"] for c in corr} == {"125", "250"}


def test_more_neighbors_than_states_say_why_the_novelty_is_empty(tiny_run, tmp_path, capsys):
    cfg, run = tiny_run
    assert main(["analyze", "--run", str(run), "--states", "6", "--modes", "training", "--checkpoint", "250",
                 "--reps", "20", "--neighbors", "100000", "--out", str(tmp_path / "knn")]) == 0
    rows = _rows(tmp_path / "knn" / "states.csv")
    assert rows and all(r["novelty_all"] in ("", "nan") for r in rows)
    assert "imssr: note: --neighbors 100000 needs more than 100000 states in the pool, which holds" \
        in capsys.readouterr().out


def test_analyze_rolls_out_the_policy_when_the_replay_has_no_physics(tiny_run, tmp_path, capsys):
    cfg, run = tiny_run
    # Rollouts on request: agent steps unknown, still every output.
    assert main(["analyze", "--run", str(run), "--states", "8", "--modes", "color_hard", "--checkpoint", "250",
                 "--source", "rollouts", "--reps", "20", "--out", str(tmp_path / "roll")]) == 0
    rows = _rows(tmp_path / "roll" / "states.csv")
    assert len(rows) == 8 and all(r["first_visit_step"] == "-1" for r in rows)

    # A replay written before physics were recorded: auto falls back to rollouts and says why.
    from imssr.rundir import RunDir
    from imssr.rundir.checkpoint import load_checkpoint

    copy = tmp_path / "old-run"
    shutil.copytree(run, copy)
    path = os.path.join(copy, "checkpoints", load_checkpoint(RunDir(str(copy)).latest).replay_file)
    frame = (3, cfg.env.image_size, cfg.env.image_size)
    full = FrameReplayBuffer(cfg.train.replay_capacity, frame, 1, physics_dim=4, warn_memory=False)
    full.load(path)
    old = FrameReplayBuffer(cfg.train.replay_capacity, frame, 1, warn_memory=False)
    old.frames, old.actions, old.rewards = full.frames, full.actions, full.rewards
    old.discounts, old.step_in_episode = full.discounts, full.step_in_episode
    old.head, old.size, old._open_episode = full.head, full.size, full._open_episode
    old.save(path)
    capsys.readouterr()
    assert main(["analyze", "--run", str(copy), "--states", "6", "--modes", "color_hard", "--checkpoint", "250",
                 "--reps", "20"]) == 0
    text = capsys.readouterr().out
    assert "fresh rollouts" in text and "before replay buffers recorded physics states" in text
    assert len(_rows(copy / "analysis" / "states.csv")) == 6
    assert main(["analyze", "--run", str(copy), "--source", "replay", "--checkpoint", "250"]) == 2
    assert "--source rollouts" in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--modes", "nope"], "unknown mode"),
    (["--modes", ","], "--modes names no scene"),
    (["--checkpoint", "999"], "no checkpoint at agent step 999"),
    (["--states", "2"], "--states must be >= 3"),
])
def test_analyze_bad_input_is_one_line(tiny_run, capsys, argv, message):
    _, run = tiny_run
    assert main(["analyze", "--run", str(run), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_analyze_refuses_a_run_without_intrinsic_reward(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(tiny_config("curl").to_json())
    assert main(["analyze", "--run", str(run)]) == 2
    assert "no intrinsic reward" in capsys.readouterr().err


def test_knn_distance_equals_a_brute_force_reference():
    # cKDTree against every pairwise distance sorted: equal up to float rounding, NaN pool rows
    # and the excluded row (the state itself) left out, NaN with fewer than k others.
    rng = np.random.default_rng(5)
    pool = rng.normal(size=(120, 4))
    pool[9] = pool[4]
    pool[::13] = np.nan
    q = np.array([i for i in range(0, 120, 7) if np.isfinite(pool[i]).all()])
    for k in (1, 2, 5):
        got = measures.knn_distance(pool[q], pool, k, exclude=q)
        for i, row in enumerate(q):
            others = [j for j in range(len(pool)) if j != row and np.isfinite(pool[j]).all()]
            ref = np.sort(np.sqrt(((pool[others] - pool[row]) ** 2).sum(axis=1)))[k - 1]
            assert got[i] == pytest.approx(ref, rel=1e-12, abs=1e-15)
    small = pool[1:4]
    assert np.isnan(measures.knn_distance(small, small, 3, exclude=np.arange(3))).all()


def test_spearman_ci_is_the_percentile_bootstrap_of_seeded_pair_resamples():
    from scipy.stats import spearmanr

    rng = np.random.default_rng(6)
    x = rng.normal(size=25)
    y = x + rng.normal(size=25)
    got = spearman_ci(x, y, 200, seed=3)
    idx = np.random.default_rng(3).integers(0, 25, size=(200, 25))
    rho = [spearmanr(x[i], y[i]).statistic for i in idx if np.ptp(x[i]) > 0 and np.ptp(y[i]) > 0]
    low, high = np.percentile(rho, [2.5, 97.5])
    assert got["ci_low"] == pytest.approx(low, abs=1e-12) and got["ci_high"] == pytest.approx(high, abs=1e-12)
