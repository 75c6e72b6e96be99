"""An agent built complete: :func:`make_agent` makes every part of a :class:`SACAgent` (its
networks, optimisers, plug-ins, generators, beta schedule and step recorder) and hands them to
it; nothing sets an attribute of an agent after it is built."""
from __future__ import annotations

from typing import Optional

import torch

from imssr.agents.generators import AgentGenerators
from imssr.agents.graphs import StepGraphs
from imssr.agents.sac import SACAgent, SACNetworks
from imssr.auxiliary import SharedNetworks, make_aux
from imssr.config import AgentConfig, AuxConfig, IntrinsicConfig
from imssr.intrinsic import BetaSchedule, IntrinsicReward, make_signal
from imssr.precision import adam, cache_frozen_weights

INDUCTOR_MODES = {"default": None, "max-autotune": "max-autotune-no-cudagraphs"}
"""``torch.compile``'s mode for each ``agent.compile`` but ``off``: kernels only, never inductor's
own CUDA graphs (``agent.cuda_graphs`` records whole steps, the compiled kernels included)."""


def make_agent(obs_shape: tuple[int, ...], action_dim: int, cfg: AgentConfig, aux_cfg: Optional[AuxConfig] = None,
               intrinsic_cfg: Optional[IntrinsicConfig] = None, device: str | torch.device = "cpu",
               seed: int = 0) -> SACAgent:
    """The agent of ``cfg`` (with the auxiliary task ``aux_cfg`` and the intrinsic reward
    ``intrinsic_cfg``, each if given and enabled) on ``device``, its weights and random streams
    seeded with ``seed``: the global generator for the initial weights, in the order networks,
    task, signal; the agent's own generators for everything it draws afterwards."""
    device = torch.device(device)
    torch.manual_seed(seed)
    nets = SACNetworks(obs_shape[0], action_dim, cfg).to(device)
    # The actor trains its projection and MLP only; the trunk is the critic's.
    optimizers = (adam(nets.critic.parameters(), cfg.critic_lr, (cfg.critic_beta1, 0.999), cfg.fused_adam),
                  adam(nets.actor.parameters(), cfg.actor_lr, (cfg.actor_beta1, 0.999), cfg.fused_adam),
                  adam([nets.log_alpha], cfg.alpha_lr, (cfg.alpha_beta1, 0.999), cfg.fused_adam))
    aux, fuse_aux = None, False
    if aux_cfg is not None:
        shared = SharedNetworks(encoder=nets.critic.encoder, target_encoder=nets.critic_target.encoder,
                                action_dim=action_dim)
        aux = make_aux(aux_cfg.name, shared, aux_cfg, cfg).to(device)
        fuse_aux = cfg.update_schedule == "fused" and aux.reads_critic_pass is not None and not aux_cfg.own_batch
        if aux.trains:
            # Fused, the critic's optimiser steps the shared encoder once on the summed gradient.
            params = aux.own_parameters() if fuse_aux else aux.trained_parameters()
            aux.optimizer = adam(params, aux_cfg.lr, fused=cfg.fused_adam)
    intrinsic = schedule = signal = None
    if intrinsic_cfg is not None and intrinsic_cfg.enabled:
        intrinsic, schedule = IntrinsicReward(intrinsic_cfg), BetaSchedule.of(intrinsic_cfg)
        signal = make_signal(intrinsic_cfg, tuple(obs_shape), cfg, aux).to(device)
    generators = AgentGenerators(seed, device)
    own = [m.optimizer for m in (aux, signal) if m is not None and m.optimizer is not None]
    graphs = StepGraphs(device, cfg.cuda_graphs, generators=generators.all(), optimizers=[*optimizers, *own])
    if cfg.compile != "off":
        compile_networks(nets, INDUCTOR_MODES[cfg.compile])
    elif cfg.precision == "bf16" and not cfg.cuda_graphs:
        # Compiled, the casts are in the graphs; eager, the frozen networks' weights would be
        # cast to bfloat16 again at every call.  Not under CUDA graphs: the cache decides in
        # Python when to cast again, which a recording would freeze (each recording casts).
        cache_frozen_weights(*(m for m in (nets, aux, signal) if m is not None))
    return SACAgent(obs_shape, action_dim, cfg, nets, optimizers, generators, graphs, aux=aux, fuse_aux=fuse_aux,
                    intrinsic=intrinsic, schedule=schedule, signal=signal)


def compile_networks(nets: SACNetworks, mode: Optional[str], backend: str = "inductor") -> None:
    """``torch.compile`` (in place: state dicts keep their keys) what the update and acting
    call, online and target: the conv trunks' two passes (:meth:`ConvTrunk.compile`), the
    projections, the Q heads and the actor's layers (:meth:`Actor.compile`)."""
    for encoder in (nets.critic.encoder, nets.critic_target.encoder):
        encoder.trunk.compile(mode=mode, backend=backend)
        encoder.projection.compile(mode=mode, backend=backend)
    for module in (nets.critic.q, nets.critic_target.q, nets.actor):
        module.compile(mode=mode, backend=backend)
