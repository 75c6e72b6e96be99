"""How closely does bf16 autocast reproduce a trained agent's Q-values and their action gradients?

    .venv/bin/python scripts/bf16_fidelity.py RUN [--checkpoint STEP] [--states 128] [--actions 16] [--split]

Loads one checkpoint of RUN (an fp32 or bf16 run: its weights are float32 either way), collects
``--states`` observations by running the deterministic policy in the run's evaluation env, and
evaluates the critic at each state for ``--actions`` actions (the policy's mean action and
uniform random ones) twice: in float32, and under the bf16 autocast that ``agent.precision=bf16``
trains with.  Prints, over states and actions:

- ``|Q|``: the size of the Q-values, and ``bf16 spacing``: the gap between neighbouring bfloat16
  numbers at that size (8 significant bits: |Q| / 128 to |Q| / 256);
- ``|dQ|``: the bf16 error of Q, ``|Q_bf16 - Q_fp32|``;
- ``action spread``: the standard deviation of Q_fp32 over the actions of one state, the part of
  Q the actor follows, and ``|dQ| / spread``;
- ``argmax agreement``: the share of states whose best action among the ``--actions`` is the same
  in both precisions;
- ``grad cosine``: the cosine between the bf16 and fp32 gradients ``dmin(Q1, Q2)/da`` at the
  policy's mean action (what the actor's loss ascends), and their norms' ratio; ``grad sign``:
  the share of (state, action dimension) pairs where the two gradients push the same way (with one
  action dimension, as cartpole's, the cosine is +1 or -1), overall and among the pairs where the
  fp32 gradient's size is in its larger half (a flip where the critic barely prefers a direction
  matters less than one where it clearly does).

``--split`` repeats the measures with only the encoder (trunk and projection) under bf16, the Q
heads in float32, and with only the Q heads under bf16: which part the error comes from.

A research aid for docs/results/dmc100k_cartpole_swingup ("bf16 below fp32"): one checkpoint, one
batch of states; the numbers describe that agent at that step, not a run.
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


def states(run, n: int, seed: int) -> torch.Tensor:
    """``n`` observations of the deterministic policy's episodes, centre-cropped, uint8."""
    env, obs_list = run.make_env(seed=seed), []
    try:
        obs, _ = env.reset(seed=seed)
        while len(obs_list) < n:
            obs_list.append(obs)
            obs, _, terminated, truncated, _ = env.step(run.act(obs, deterministic=True))
            if terminated or truncated:
                obs, _ = env.reset()
    finally:
        env.close()
    x = torch.as_tensor(np.stack(obs_list), device=run.agent.device)
    return center_crop(x, run.agent.cfg.crop_size)


def q_and_grad(agent, x: torch.Tensor, actions: torch.Tensor, encoder: str, head: str):
    """Q1 of every (state, action) pair, ``(S, K)``, and ``d min(Q1, Q2) / da`` at ``actions[:, 0]``,
    with the encoder (trunk and projection) at precision ``encoder`` and the Q heads at ``head``."""
    nets, (s, k, a_dim) = agent.nets, actions.shape
    with torch.no_grad(), autocast(agent.device, encoder):
        z = nets.critic.encoder.projection(nets.critic.encoder.trunk(x)).float()
    with torch.no_grad(), autocast(agent.device, head):
        q1, _ = nets.critic.q(z.repeat_interleave(k, 0), actions.reshape(s * k, a_dim))
    a0 = actions[:, 0].clone().requires_grad_(True)
    with autocast(agent.device, head):
        g1, g2 = nets.critic.q(z, a0)
        q_min = torch.min(g1.float(), g2.float()).sum()
    (grad,) = torch.autograd.grad(q_min, a0)
    return q1.float().reshape(s, k), grad.float()


def measure(run, n_states: int = 128, n_actions: int = 16, seed: int = 0,
            encoder: str = "bf16", head: str = "bf16") -> dict:
    """The measures printed by :func:`main`, as numbers (see the module's docstring), of the
    encoder at precision ``encoder`` and the Q heads at ``head`` against both in fp32."""
    torch.manual_seed(seed)
    agent = run.agent
    agent.nets.eval()
    x = states(run, n_states, seed)
    with torch.no_grad():
        mean = agent.nets.actor(agent.nets.critic.encoder.trunk(x), sample=False).mean
    random = torch.rand(len(x), n_actions - 1, mean.shape[-1], device=x.device) * 2 - 1
    actions = torch.cat([mean.unsqueeze(1), random], dim=1)
    q32, g32 = q_and_grad(agent, x, actions, "fp32", "fp32")
    q16, g16 = q_and_grad(agent, x, actions, encoder, head)
    err, spread, size = (q16 - q32).abs(), q32.std(dim=1, unbiased=False), q32.abs()
    big = g32.abs() >= g32.abs().median()  # the larger half of |dQ/da|, over (state, dimension)
    return {
        "states": len(x), "actions": n_actions,
        "q_median": size.median().item(), "q_max": size.max().item(),
        "spacing_at_median": 2.0 ** (torch.floor(torch.log2(size.median())).item() - 7),
        "err_mean": err.mean().item(), "err_median": err.median().item(), "err_max": err.max().item(),
        "spread_median": spread.median().item(),
        "err_over_spread_median": (err.mean(1) / spread.clamp_min(1e-12)).median().item(),
        "argmax_agreement": (q16.argmax(1) == q32.argmax(1)).float().mean().item(),
        "grad_cosine_median": torch.nn.functional.cosine_similarity(g16, g32, dim=-1).median().item(),
        "grad_norm_ratio_median": (g16.norm(dim=-1) / g32.norm(dim=-1).clamp_min(1e-12)).median().item(),
        "grad_sign_same": (torch.sign(g16) == torch.sign(g32)).float().mean().item(),
        "grad_sign_same_larger_half": (torch.sign(g16) == torch.sign(g32))[big].float().mean().item(),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run")
    p.add_argument("--checkpoint", default=None, help="agent step of a retained step-*.pt (default: latest)")
    p.add_argument("--states", type=int, default=128)
    p.add_argument("--actions", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", action="store_true",
                   help="also the encoder alone in bf16 (Q heads fp32) and the Q heads alone in bf16")
    a = p.parse_args(argv)
    if a.states < 2 or a.actions < 2:
        print("bf16_fidelity: --states and --actions must be at least 2", file=sys.stderr)
        return 2
    try:
        run = imssr.load_run(a.run, checkpoint=a.checkpoint)
    except ImssrError as e:
        print(f"bf16_fidelity: {e}", file=sys.stderr)
        return 2
    parts = [("bf16", "bf16")] + ([("bf16", "fp32"), ("fp32", "bf16")] if a.split else [])
    for encoder, head in parts:
        m = measure(run, a.states, a.actions, a.seed, encoder, head)
        print(f"{run!r}: {m['states']} states x {m['actions']} actions; encoder {encoder}, Q heads {head}")
        print(f"  |Q|               median {m['q_median']:.3f}  max {m['q_max']:.3f}  "
              f"bf16 spacing at the median {m['spacing_at_median']:.4f}")
        print(f"  |dQ| vs fp32      mean {m['err_mean']:.4f}  median {m['err_median']:.4f}  max {m['err_max']:.4f}")
        print(f"  action spread     median {m['spread_median']:.4f}  (std of Q over one state's actions)")
        print(f"  |dQ| / spread     median {m['err_over_spread_median']:.4f}")
        print(f"  argmax agreement  {m['argmax_agreement']:.3f} of states")
        print(f"  grad cosine       median {m['grad_cosine_median']:.4f};  "
              f"norm ratio median {m['grad_norm_ratio_median']:.4f}")
        print(f"  grad sign         the same in {m['grad_sign_same']:.3f} of (state, action dimension) pairs, "
              f"{m['grad_sign_same_larger_half']:.3f} of those with the larger half of |dQ/da|")
    return 0

if __name__ == "__main__":
    sys.exit(main())
