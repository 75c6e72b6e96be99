"""What bf16 autocast changes in what a trained agent's actor uses from its critic.

    .venv/bin/python scripts/bf16_fidelity.py RUN [--checkpoints 250 1000 ...] [--episodes 4]
        [--states-per-episode 32] [--actions 33] [--split] [--seed 0]

For each checkpoint (``--checkpoints``: agent steps of retained ``step-*.pt``; default: every
retained one, oldest first) the script collects states from ``--episodes`` episodes of that
checkpoint's deterministic policy in the run's evaluation env (``--states-per-episode`` evenly
spaced states each) and compares the critic at those states in float32 with the critic under the
bf16 autocast that ``agent.precision=bf16`` trains with.  Two things that would otherwise dominate
the comparison are kept out: **the final layer of each Q head runs in float32** on the bf16 hidden
features (the rounding of Q's own output to bfloat16, about |Q| / 256, is not what the actor
follows), and every comparison is made in float32 on ``min(Q1, Q2)``, the actor's objective.
Measured, per checkpoint:

- ``dQ/da``: the gradient of ``min(Q1, Q2)`` at the policy's mean action, the direction the actor's
  loss ascends: the share of (state, action dimension) pairs where bf16 and fp32 push the same
  way, overall and among the pairs in the larger half of the fp32 gradient's size, and the median
  cosine between the two gradients (for a one-dimensional action the cosine is the sign);
- **regret**: over ``--actions`` candidate actions per state (an even grid for a one-dimensional
  action, else the mean action and uniform random ones), the action bf16 ranks best, scored by the
  fp32 critic: ``max_a Q32(a) - Q32(argmax_a Q16(a))``, as the share of states where it is above
  zero and its median and 95th percentile divided by the state's fp32 spread of Q over the
  candidates (max - min): 0 means bf16 picks an action fp32 values as highly, 1 the worst one.

``--split`` repeats it with only the encoder (trunk and projection) under bf16 and with only the
Q heads' hidden layers under bf16.  Prints a Markdown table, one row per checkpoint and part.
A research aid for docs/results/dmc100k_cartpole_swingup ("bf16 and fp32").
"""
from __future__ import annotations

import argparse
import sys

import numpy as np
import torch

import imssr
from imssr.augmentations import center_crop
from imssr.errors import ImssrError
from imssr.precision import autocast
from imssr.rundir import RunDir


def states(run, episodes: int, per_episode: int, seed: int) -> torch.Tensor:
    """``per_episode`` evenly spaced observations of each of ``episodes`` episodes of the
    deterministic policy (seeds ``seed``, ``seed + 1``, ...), centre-cropped, uint8."""
    picked = []
    env = run.make_env(seed=seed)
    try:
        for e in range(episodes):
            obs, _ = env.reset(seed=seed + e)
            seen, done = [], False
            while not done:
                seen.append(obs)
                obs, _, terminated, truncated, _ = env.step(run.act(obs, deterministic=True))
                done = terminated or truncated
            idx = np.linspace(0, len(seen) - 1, min(per_episode, len(seen))).round().astype(int)
            picked += [seen[i] for i in idx]
    finally:
        env.close()
    x = torch.as_tensor(np.stack(picked), device=run.agent.device)
    return center_crop(x, run.agent.cfg.crop_size)


def head_min_q(q_heads, z: torch.Tensor, action: torch.Tensor, precision: str, device) -> torch.Tensor:
    """``min(Q1, Q2)`` in float32, the heads' hidden layers at ``precision`` and their final
    layer in float32."""
    za = torch.cat([z, action], dim=-1)
    out = []
    for head in (q_heads.q1, q_heads.q2):
        *hidden, last = list(head)
        with autocast(device, precision):
            h = za
            for layer in hidden:
                h = layer(h)
        out.append(last(h.float()))
    return torch.min(out[0], out[1]).squeeze(-1).float()


def candidates(mean: torch.Tensor, k: int, generator: torch.Generator) -> torch.Tensor:
    """``(S, K, |A|)`` candidate actions per state: an even grid of [-1, 1] for one action
    dimension, else the mean action and ``K - 1`` uniform random ones."""
    s, a_dim = mean.shape
    if a_dim == 1:
        grid = torch.linspace(-1, 1, k, device=mean.device)
        return grid.view(1, k, 1).expand(s, k, 1).clone()
    rand = torch.rand(s, k - 1, a_dim, generator=generator, device=mean.device) * 2 - 1
    return torch.cat([mean.unsqueeze(1), rand], dim=1)


def evaluate(agent, x: torch.Tensor, actions: torch.Tensor, mean: torch.Tensor, encoder: str, head: str):
    """``(Q over the candidates (S, K), dQ/da at the mean action (S, |A|))``."""
    critic, device = agent.nets.critic, agent.device
    with torch.no_grad(), autocast(device, encoder):
        z = critic.encoder.projection(critic.encoder.trunk(x))
    z = z.float()
    s, k, a_dim = actions.shape
    with torch.no_grad():
        q = head_min_q(critic.q, z.repeat_interleave(k, 0), actions.reshape(s * k, a_dim), head, device).reshape(s, k)
    a0 = mean.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(head_min_q(critic.q, z, a0, head, device).sum(), a0)
    return q, grad.float()


def measure(run, x: torch.Tensor, n_actions: int, seed: int, encoder: str, head: str) -> dict:
    agent = run.agent
    agent.nets.eval()
    with torch.no_grad():
        mean = agent.nets.actor(agent.nets.critic.encoder.trunk(x), sample=False).mean.float()
    actions = candidates(mean, n_actions, torch.Generator(device=x.device).manual_seed(seed))
    q32, g32 = evaluate(agent, x, actions, mean, "fp32", "fp32")
    q16, g16 = evaluate(agent, x, actions, mean, encoder, head)
    spread = (q32.max(1).values - q32.min(1).values).clamp_min(1e-12)
    picked = q32.gather(1, q16.argmax(1, keepdim=True)).squeeze(1)
    regret = (q32.max(1).values - picked) / spread
    same = torch.sign(g16) == torch.sign(g32)
    big = g32.abs() >= g32.abs().median()
    return {
        "q_median": q32.abs().median().item(), "spread_median": spread.median().item(),
        "sign_same": same.float().mean().item(), "sign_same_larger_half": same[big].float().mean().item(),
        "cosine_median": torch.nn.functional.cosine_similarity(g16, g32, dim=-1).median().item(),
        "regret_share": (regret > 0).float().mean().item(), "regret_median": regret.median().item(),
        "regret_p95": torch.quantile(regret, 0.95).item(),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--checkpoints", nargs="+", help="agent steps of retained step-*.pt (default: all, oldest first)")
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--states-per-episode", type=int, default=32)
    p.add_argument("--actions", type=int, default=33, help="candidate actions per state for the regret")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", action="store_true",
                   help="also the encoder alone under bf16, and the Q heads' hidden layers alone")
    a = p.parse_args(argv)
    if a.episodes < 1 or a.states_per_episode < 2 or a.actions < 2:
        print("bf16_fidelity: --episodes must be at least 1, --states-per-episode and --actions at least 2",
              file=sys.stderr)
        return 2
    try:
        steps = a.checkpoints or [str(s) for s in RunDir(a.run).checkpoint_steps()]
        if not steps:
            raise ImssrError(f"{a.run} has no retained step-*.pt checkpoint")
        loaded = [(step, imssr.load_run(a.run, checkpoint=step)) for step in steps]
    except ImssrError as e:
        print(f"bf16_fidelity: {e}", file=sys.stderr)
        return 2
    parts = [("bf16", "bf16")] + ([("bf16", "fp32"), ("fp32", "bf16")] if a.split else [])
    print(f"# bf16_fidelity: {a.run}; {a.episodes} episodes x {a.states_per_episode} states per checkpoint, "
          f"{a.actions} candidate actions; Q heads' final layer and every comparison in float32")
    print("| agent step | under bf16 | median \\|Q\\| | median spread of Q over the candidates | dQ/da same sign "
          "(larger half) | dQ/da cosine, median | states where bf16's pick loses | regret / spread: median, 95th pct |")
    print("|---:|---|---:|---:|---|---:|---:|---|")
    for step, run in loaded:
        torch.manual_seed(a.seed)
        x = states(run, a.episodes, a.states_per_episode, a.seed)
        for encoder, head in parts:
            m = measure(run, x, a.actions, a.seed, encoder, head)
            what = {("bf16", "bf16"): "encoder and Q heads", ("bf16", "fp32"): "encoder only",
                    ("fp32", "bf16"): "Q heads only"}[encoder, head]
            print(f"| {int(step):,} | {what} | {m['q_median']:.2f} | {m['spread_median']:.3f} | "
                  f"{m['sign_same']:.3f} ({m['sign_same_larger_half']:.3f}) | {m['cosine_median']:.3f} | "
                  f"{m['regret_share']:.3f} | {m['regret_median']:.4f}, {m['regret_p95']:.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
