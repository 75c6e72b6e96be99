"""Pixel SAC with a pluggable auxiliary task and an optional intrinsic reward.

One agent step's update, :meth:`SACAgent.update` (order as in the CURL / DMC-GB code bases):
  1. critic, every ``critic_update_every`` steps: ``encode`` the batch once, ``bellman_target``
     on ``r + beta_t * r_int``, ``critic_loss`` over the observation views the auxiliary task
     asks for (SVEA: clean + augmented);
  2. actor and temperature, every ``actor_update_every`` steps;
  3. soft update of the target Q heads (``critic_tau``) and target encoder
     (``encoder_tau``), every ``target_update_every`` steps;
  4. the auxiliary task, every ``aux.update_every`` steps;
  5. the intrinsic signal's own networks, if it has any (RND's predictor).
``agent.update_schedule`` picks one of two paths, each read top to bottom:
:meth:`SACAgent.update_sequential` (the reference) and :meth:`SACAgent.update_fused` (the actor
reuses the critic's encoding of ``o``; a task that can read the critic's pass adds its loss to
the critic's backward in step 1).
The time limit is not terminal: ``discount`` is 0 only for true terminal states.
"""
from __future__ import annotations

import copy
import math
from dataclasses import replace
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from imssr import draws
from imssr.agents.graphs import StepGraphs, set_capturable
from imssr.augmentations import center_crop, random_crop
from imssr.auxiliary import AuxiliaryTask, SharedNetworks, make_aux
from imssr.batch import Batch, Encoding, NextObsContext
from imssr.config import AgentConfig, AuxConfig, IntrinsicConfig
from imssr.errors import ImssrError
from imssr.intrinsic import IntrinsicReward, IntrinsicSignal, make_signal
from imssr.networks import Actor, ConvTrunk, Critic, Encoder, ema, weight_init
from imssr.precision import (adam, autocast, cache_frozen_weights, configure_cuda, full_precision, optimizer_step,
                             upcast, warn_if_bf16_is_slow)
from imssr.replay import FrameReplayBuffer
from imssr.seeds import INTRINSIC_SEED_OFFSET, NOISE_SEED_OFFSET

Metrics = dict[str, "torch.Tensor | float"]

Inputs = dict[str, "torch.Tensor | dict[str, torch.Tensor]"]
"""What one update reads besides the agent's own state: ``sample`` (the RL batch from the replay
buffer), ``aux_sample`` (the auxiliary task's own batch, when it trains on one at this step) and,
under ``agent.cuda_graphs``, ``beta`` (``beta_t`` as a float64 tensor; otherwise the intrinsic
reward reads its schedule)."""

INDUCTOR_MODES = {"default": None, "max-autotune": "max-autotune-no-cudagraphs"}
"""``torch.compile``'s mode for each ``agent.compile`` but ``off``: kernels only, never inductor's
own CUDA graphs (``agent.cuda_graphs`` records whole steps, the compiled kernels included)."""

GENERATORS = (("gen", 0), ("noise_gen", NOISE_SEED_OFFSET), ("intrinsic_gen", INTRINSIC_SEED_OFFSET))
"""An agent's generators (attribute and state-dict key) with the offset of each one's seed from
the run's (:mod:`imssr.seeds`): augmentation, policy noise, the intrinsic signal's extra views."""


def restore_generators(gens: dict[str, torch.Generator], state: dict, updates: int) -> None:
    """Set each of :data:`GENERATORS` (``gens``, by key) from ``state``.  A state written on
    another device type (CPU and CUDA generator states differ) reseeds it instead, at its seed
    plus ``updates``: an exact resume across device types is impossible anyway."""
    seed = int(gens["gen"].initial_seed())
    for key, offset in GENERATORS:
        try:
            gens[key].set_state(state[key])
        except RuntimeError:  # saved on another device type
            gens[key].manual_seed(seed + offset + updates)


class Eager:
    """How an agent runs the pieces of its update: as they are, for one agent.

    A batch of member agents (:class:`imssr.agents.batched.AgentBatch`) swaps in its own, which
    runs each piece for all members (vmapped over their stacked weights, or member after member),
    so that the update's schedule below is written once for both."""

    def call(self, fn, *args):
        """``fn(*args)``: a piece that computes losses or a batch (random draws included)."""
        return fn(*args)

    def step(self, loss: torch.Tensor, *optimizers: torch.optim.Optimizer) -> None:
        """Backpropagate ``loss`` and step ``optimizers`` (:func:`~imssr.precision.optimizer_step`)."""
        optimizer_step(loss, *optimizers)

    def read(self, fn):
        """``fn()``: a piece that reads or updates weights element by element (soft target
        updates, the temperature)."""
        return fn()


class SACNetworks(nn.Module):
    """Critic (owning the conv trunk), its target copy, the actor and log alpha."""

    def __init__(self, obs_channels: int, action_dim: int, cfg: AgentConfig):
        super().__init__()
        trunk = ConvTrunk(obs_channels, cfg.crop_size, cfg.encoder_layers, cfg.encoder_filters,
                          cfg.encoder_head_layers, cfg.channels_last, cfg.final_relu)
        self.critic = Critic(Encoder(trunk, cfg.feature_dim, cfg.projection_tanh), action_dim, cfg.hidden_dim,
                             q_heads_fp32=cfg.q_heads_fp32)
        self.actor = Actor(trunk.out_dim, cfg.feature_dim, action_dim, cfg.hidden_dim,
                           cfg.log_std_min, cfg.log_std_max, cfg.projection_tanh)
        self.apply(weight_init)
        self.critic_target = copy.deepcopy(self.critic)
        for p in self.critic_target.parameters():
            p.requires_grad_(False)
        self.log_alpha = nn.Parameter(torch.tensor(math.log(cfg.init_temperature)))


class SACAgent:
    """SAC from pixels; ``aux`` and ``intrinsic`` are plug-ins."""

    def __init__(self, obs_shape: tuple[int, ...], action_dim: int, cfg: AgentConfig,
                 aux_cfg: Optional[AuxConfig] = None, intrinsic_cfg: Optional[IntrinsicConfig] = None,
                 device: str | torch.device = "cpu", seed: int = 0):
        self.cfg = cfg
        self.device = torch.device(device)
        self.action_dim = action_dim
        self.obs_shape = tuple(obs_shape)
        torch.manual_seed(seed)
        self.nets = SACNetworks(obs_shape[0], action_dim, cfg).to(self.device)
        n = self.nets
        self.target_entropy = -float(action_dim)
        self.critic_opt = adam(n.critic.parameters(), cfg.critic_lr, (cfg.critic_beta1, 0.999), cfg.fused_adam)
        # The actor trains its projection and MLP only; the trunk is the critic's.
        self.actor_opt = adam(n.actor.parameters(), cfg.actor_lr, (cfg.actor_beta1, 0.999), cfg.fused_adam)
        self.alpha_opt = adam([n.log_alpha], cfg.alpha_lr, (cfg.alpha_beta1, 0.999), cfg.fused_adam)
        self.aux: Optional[AuxiliaryTask] = None
        self.fuse_aux = False
        """Whether the task's loss is read from the critic's pass and joins its backward: the fused
        schedule, a task that can (:attr:`AuxiliaryTask.reads_critic_pass`), on the RL batch (a
        batch of its own needs a pass of its own)."""
        if aux_cfg is not None:
            shared = SharedNetworks(encoder=n.critic.encoder, target_encoder=n.critic_target.encoder,
                                    action_dim=action_dim)
            self.aux = make_aux(aux_cfg.name, shared, aux_cfg, cfg).to(self.device)
            self.fuse_aux = (cfg.update_schedule == "fused" and self.aux.reads_critic_pass is not None
                             and not aux_cfg.own_batch)
            if self.aux.trains:
                # Fused, the critic's optimiser steps the shared encoder once on the summed gradient.
                params = self.aux.own_parameters() if self.fuse_aux else self.aux.trained_parameters()
                self.aux.optimizer = adam(params, aux_cfg.lr, fused=cfg.fused_adam)
        self.intrinsic: Optional[IntrinsicReward] = None
        self.signal: Optional[IntrinsicSignal] = None
        if intrinsic_cfg is not None and intrinsic_cfg.enabled:
            self.intrinsic = IntrinsicReward(intrinsic_cfg)
            self.signal = make_signal(intrinsic_cfg, self.obs_shape, cfg, self.aux).to(self.device)
        # Separate generators: augmentations/policy noise, and the intrinsic
        # reward's extra views, so that computing r_int never shifts the
        # random stream of the base algorithm (beta = 0 is the baseline exactly).
        # All on the agent's device: crop offsets, overlay indices and kernels are drawn where
        # they are used, with no copy from the host in an update.
        self.gen = torch.Generator(device=self.device).manual_seed(seed)
        self.noise_gen = torch.Generator(device=self.device).manual_seed(seed + NOISE_SEED_OFFSET)
        self.intrinsic_gen = torch.Generator(device=self.device).manual_seed(seed + INTRINSIC_SEED_OFFSET)
        self.updates = 0
        self.run = Eager()
        """Runs the update's pieces (:class:`Eager`; a batch of members swaps in its own)."""
        warn_if_bf16_is_slow(self.device, cfg.precision)
        configure_cuda(self.device, cfg.tf32)
        self.graphs = StepGraphs(self.device, cfg.cuda_graphs, generators=self.generators,
                                 prepare=lambda: set_capturable(self.optimizers(), True))
        """Runs :meth:`update_on` and :meth:`act_on`: directly, or recorded as CUDA graphs under
        ``agent.cuda_graphs`` (:mod:`imssr.agents.graphs`)."""
        if cfg.compile != "off":
            self._compile(INDUCTOR_MODES[cfg.compile])
        elif cfg.precision == "bf16" and not cfg.cuda_graphs:
            # Compiled, the casts are in the graphs; eager, the frozen networks' weights would be
            # cast to bfloat16 again at every call.  Not under CUDA graphs: the cache decides in
            # Python when to cast again, which a recording would freeze (each recording casts).
            cache_frozen_weights(*(m for m in (self.nets, self.aux, self.signal) if m is not None))

    def _compile(self, mode: Optional[str], backend: str = "inductor") -> None:
        """``torch.compile`` (in place: state dicts keep their keys) what the update and acting
        call, online and target: the conv trunks' two passes (:meth:`ConvTrunk.compile`), the
        projections, the Q heads and the actor's layers (:meth:`Actor.compile`)."""
        n = self.nets
        for encoder in (n.critic.encoder, n.critic_target.encoder):
            encoder.trunk.compile(mode=mode, backend=backend)
            encoder.projection.compile(mode=mode, backend=backend)
        for module in (n.critic.q, n.critic_target.q, n.actor):
            module.compile(mode=mode, backend=backend)

    def generators(self) -> list[torch.Generator]:
        """Every generator an update or action draws from (a batch's members' own included):
        what a CUDA graph registers."""
        gens = []
        for g in (self.gen, self.noise_gen, self.intrinsic_gen):
            gens += g.generators if isinstance(g, draws.MemberGenerators) else [g]
        return gens

    def optimizers(self) -> list[torch.optim.Optimizer]:
        """The agent's optimisers, SAC's then the auxiliary task's and the signal's: one order for
        every agent of a configuration (a batch of members pairs them by it)."""
        opts = [self.critic_opt, self.actor_opt, self.alpha_opt]
        return opts + [m.optimizer for m in (self.aux, self.signal) if m is not None and m.optimizer is not None]

    def autocast(self):
        """The context of the agent's forward passes: bfloat16 autocast under
        ``agent.precision = bf16`` (:mod:`imssr.precision`), else none."""
        return autocast(self.device, self.cfg.precision)

    @property
    def alpha(self) -> torch.Tensor:
        return self.nets.log_alpha.exp()

    # -- acting ------------------------------------------------------------------
    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool) -> np.ndarray:
        """Action in [-1, 1] for one stacked uint8 observation (centre crop)."""
        x = torch.as_tensor(obs, device=self.device).unsqueeze(0)
        action = self.graphs(("act", deterministic), lambda inputs: self.act_on(inputs, deterministic), {"obs": x})
        return action[0].cpu().numpy().astype(np.float32)

    def act_on(self, inputs: dict[str, torch.Tensor], deterministic: bool) -> torch.Tensor:
        """:meth:`policy_action` on ``inputs["obs"]`` (what :meth:`act` runs or records)."""
        with torch.no_grad(), self.autocast():
            return self.run.call(self.policy_action, inputs["obs"], deterministic)

    def policy_action(self, obs: torch.Tensor, deterministic: bool) -> torch.Tensor:
        """Actions ``(B, |A|)`` for a batch of uint8 observation stacks (centre crop); a sample
        from :attr:`noise_gen` unless ``deterministic``."""
        trunk = self.nets.critic.encoder.trunk(center_crop(obs, self.cfg.crop_size))
        return self.nets.actor(trunk, generator=self.noise_gen, sample=not deterministic).action

    # -- learning ----------------------------------------------------------------
    def to_batch(self, sample: dict[str, np.ndarray | torch.Tensor]) -> Batch:
        """The update's :class:`Batch` from a replay sample: arrays, or tensors already on the
        agent's device (:meth:`FrameReplayBuffer.sample_batch`, taken as they are)."""
        d = self.device
        sample = {k: torch.as_tensor(sample[k], device=d) for k in ("obs", "next_obs", "action", "reward", "discount")}
        return Batch(**self.run.call(self.crop_batch, sample), generator=self.gen)

    def crop_batch(self, sample: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The :class:`Batch` fields of a sample on the agent's device: the RL crops of o and o'
        (drawn from :attr:`gen`, o first), the transition's fields as columns."""
        size = self.cfg.crop_size
        return dict(obs=random_crop(sample["obs"], size, self.gen),
                    action=sample["action"], reward=sample["reward"].unsqueeze(-1),
                    discount=sample["discount"].unsqueeze(-1),
                    next_obs=random_crop(sample["next_obs"], size, self.gen),
                    raw_obs=sample["obs"], raw_next_obs=sample["next_obs"])

    def update(self, replay: FrameReplayBuffer, step: int) -> Metrics:
        """All updates of one agent step; ``step`` counts agent steps.  Metrics stay on the
        device (the training loop reads them once per episode): no host sync in an update.
        The replay samples are drawn here, the RL batch's first, and the update proper
        (:meth:`update_on`) reads them: one recording per :meth:`update_key` under CUDA graphs."""
        inputs: Inputs = {"sample": replay.sample_batch(self.cfg.batch_size, self.device)}
        if self.aux_due(step) and self.aux.cfg.own_batch:
            inputs["aux_sample"] = replay.sample_batch(self.aux.cfg.batch_size, self.device)
        if self.graphs.enabled and self.intrinsic is not None:
            inputs["beta"] = self.intrinsic.schedule.tensor(step, self.device)
        metrics = self.graphs(("update", *self.update_key(step)), lambda x: self.update_on(x, step), inputs)
        self.updates += 1
        return metrics

    def update_key(self, step: int) -> tuple[bool, ...]:
        """Which parts of the update run at agent step ``step``: the critic, the actor and
        temperature, the target EMA, the auxiliary task.  Everything else an update does is the
        same at every step."""
        c = self.cfg
        return (step % c.critic_update_every == 0, step % c.actor_update_every == 0,
                step % c.target_update_every == 0, self.aux_due(step))

    def update_on(self, inputs: Inputs, step: int) -> Metrics:
        """The update of agent step ``step`` on its replay samples (:data:`Inputs`)."""
        batch = self.to_batch(inputs["sample"])
        with self.autocast():
            if self.cfg.update_schedule == "fused":
                metrics = self.update_fused(inputs, batch, step)
            else:
                metrics = self.update_sequential(inputs, batch, step)
            if self.signal is not None:
                metrics.update(self.update_signal(batch, step))
        return metrics

    def update_sequential(self, inputs: Inputs, batch: Batch, step: int) -> Metrics:
        """The CURL / DMC-GB order: critic; actor on a fresh encoding of o after the critic's
        step; target EMA; the auxiliary task on passes of its own."""
        c, metrics, run = self.cfg, {}, self.run
        if step % c.critic_update_every == 0:
            loss, critic_metrics = run.call(self.critic_objective, batch, step, inputs.get("beta"))
            run.step(loss, self.critic_opt)
            metrics.update(critic_metrics)
        if step % c.actor_update_every == 0:
            actor_loss, alpha_loss, entropy = run.call(self.actor_objective, batch)
            metrics.update(self.step_actor_and_alpha(actor_loss, alpha_loss, entropy))
        if step % c.target_update_every == 0:
            run.read(self.soft_update_targets)
        if self.aux_due(step):
            metrics.update(self.update_aux(inputs, batch, step))
        return metrics

    def update_fused(self, inputs: Inputs, batch: Batch, step: int) -> Metrics:
        """One online pass over o serves the critic, the actor (the encoding from before the
        critic's step, detached, as DrQ-v2) and a task that reads it (CURL, PAD): its loss
        joins the critic's backward, each optimiser stepping its own parameters (the shared
        encoder's once, the critic's, on the summed gradient).  Needs
        ``critic_update_every = 1`` (validated)."""
        c, run = self.cfg, self.run
        fuse = self.fuse_aux and self.aux_due(step)
        loss, metrics, trunk = run.call(self.fused_objective, batch, step, inputs.get("beta"), fuse)
        run.step(loss, self.critic_opt, *([self.aux.optimizer] if fuse else []))
        if fuse:
            run.read(lambda: self.aux.after_step(step))
        if step % c.actor_update_every == 0:
            metrics.update(self.step_actor_and_alpha(*run.call(self.actor_losses, trunk)))
        if step % c.target_update_every == 0:
            run.read(self.soft_update_targets)
        if self.aux_due(step) and not fuse:
            metrics.update(self.update_aux(inputs, batch, step))
        return metrics

    def critic_objective(self, batch: Batch, step: int,
                         beta: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, Metrics]:
        """The sequential schedule's critic loss (:meth:`critic_loss` on a fresh :meth:`encode`
        of ``batch`` and its :meth:`bellman_target`) and its metrics."""
        loss, metrics, _ = self.fused_objective(batch, step, beta, with_task_loss=False)
        return loss, metrics

    def fused_objective(self, batch: Batch, step: int, beta: Optional[torch.Tensor],
                        with_task_loss: bool) -> tuple[torch.Tensor, Metrics, torch.Tensor]:
        """The critic's loss on one :meth:`encode` of ``batch`` and its :meth:`bellman_target`,
        plus the task's mean per-sample loss read from the same pass if ``with_task_loss``; the
        metrics; and that pass's trunk of o, detached (the fused schedule's actor input)."""
        enc = self.encode(batch, with_task_loss=with_task_loss)
        target_q, metrics = self.bellman_target(batch, enc, step, beta)
        loss, q_mean = self.critic_loss(batch, enc, target_q)
        if with_task_loss:  # its metric before the critic's, as the fused update always listed them
            aux_loss = enc.aux_loss.mean()
            metrics["aux_loss"] = aux_loss.detach()
        metrics.update(critic_loss=loss.detach(), q_mean=q_mean)
        return (loss + aux_loss if with_task_loss else loss), metrics, enc.obs_trunk.detach()

    def actor_objective(self, batch: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The sequential schedule's actor and temperature losses on a fresh encoding of o after
        the critic's step (:meth:`actor_losses`)."""
        with torch.no_grad():  # the actor never trains the convolutions: no graph
            trunk = self.nets.critic.encoder.trunk(batch.obs)
        return self.actor_losses(trunk)

    def encode(self, batch: Batch, with_task_loss: bool = False) -> Encoding:
        """The update's encoder passes (:class:`~imssr.batch.Encoding`): the online trunk over
        the critic's views of o in one pass, with grad; o' through the online trunk and the
        target encoder, without.  ``with_task_loss``: the auxiliary task's per-sample loss read
        from this pass too (``Encoding.aux_loss``; PAD's also needs o' with grad, in the same
        pass).  Computed before the Bellman target, whose intrinsic signal may reuse it (IM-PAD);
        the two draw from different generators, so the order changes no random draw."""
        trunk_net = self.nets.critic.encoder.trunk
        views = self.aux.critic_views(batch) if self.aux is not None else [(batch.obs, 1.0)]
        obs = views[0][0] if len(views) == 1 else torch.cat([v for v, _ in views])
        next_features = None
        if with_task_loss and self.aux.reads_critic_pass == "obs+next_obs":
            both = trunk_net.shared_features(torch.cat([obs, batch.next_obs]))
            features, next_features = both[:len(obs)], both[len(obs):]
        else:
            features = trunk_net.shared_features(obs)
        with torch.no_grad():
            next_trunk = trunk_net(batch.next_obs) if next_features is None \
                else trunk_net.head_features(next_features.detach())
            next_latent = self.nets.critic_target.encoder(batch.next_obs)
        enc = Encoding(view_weights=tuple(w for _, w in views), features=features,
                       trunk=trunk_net.head_features(features),  # = trunk_net(obs)
                       next_trunk=next_trunk, next_latent=next_latent, next_features=next_features)
        if with_task_loss:
            enc = replace(enc, aux_loss=self.aux.per_sample_loss(batch, enc))
        return enc

    @torch.no_grad()
    def bellman_target(self, batch: Batch, enc: Encoding, step: int,
                       beta: Optional[torch.Tensor] = None) -> tuple[torch.Tensor, Metrics]:
        """``y = r + beta_t * r_int + gamma * d * (min_i Q*_i(z*', a') - alpha log pi(a'|o'))``,
        ``a' ~ pi(. | o')``, and the intrinsic reward's statistics.  The reward is the paper's
        Eq. (1) with Algorithm 1's ``r_int``: the signal of o', normalised in the batch.
        ``beta``: ``beta_t`` as a tensor (CUDA graphs), else the schedule's value at ``step``."""
        n = self.nets
        next_policy = n.actor(enc.next_trunk, generator=self.noise_gen)
        tq1, tq2 = n.critic_target.q(enc.next_latent, next_policy.action)
        reward, stats = batch.reward, {}
        if self.intrinsic is not None:
            bonus, stats = self.intrinsic(self.intrinsic_signal(batch, enc), step, beta)
            reward = reward + bonus
        with full_precision(tq1):
            # y in float32: r + beta r_int + gamma V' adds terms of different scales, and every
            # regression of this update aims at it.
            target_v = torch.min(upcast(tq1), upcast(tq2)) - self.alpha * next_policy.log_prob
            return reward + batch.discount * self.cfg.discount * target_v, stats

    @torch.no_grad()
    def intrinsic_signal(self, batch: Batch, enc: Encoding) -> torch.Tensor:
        """The raw per-sample signal of o' (the task's loss, RND's error, RE3's distance),
        ``(B,)``, before normalisation and beta; draws fresh views from ``intrinsic_gen`` only."""
        if self.signal is None:
            raise ImssrError("this agent has no intrinsic signal (intrinsic.enabled is false)")
        ctx = NextObsContext(batch=batch, enc=enc, generator=self.intrinsic_gen, form=self.intrinsic.cfg.form)
        return self.signal(ctx)

    def critic_loss(self, batch: Batch, enc: Encoding, target_q: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``sum_v w_v (||Q1(z_v, a) - y||^2 + ||Q2(z_v, a) - y||^2)`` over the views of o, each
        regressed to the same clean target (one view of weight 1 unless a task adds some: SVEA's
        Eq. L_SVEA), and the mean Q1 of ``batch.obs`` (detached)."""
        n, views = self.nets, len(enc.view_weights)
        q1_all, q2_all = n.critic.q(n.critic.encoder.projection(enc.trunk), batch.action.repeat(views, 1))
        with full_precision(q1_all):  # the TD errors against the float32 target, in float32
            q1_all, q2_all = upcast(q1_all), upcast(q2_all)
            loss = 0.0
            for q1, q2, weight in zip(q1_all.chunk(views), q2_all.chunk(views), enc.view_weights, strict=True):
                loss = loss + weight * (F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q))
            return loss, q1_all[:len(batch)].detach().mean()

    def actor_losses(self, trunk: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """SAC's policy and temperature losses on ``trunk``, the online trunk's output on
        ``batch.obs`` without a graph, and the policy's mean entropy.  The temperature's loss
        reads log pi detached and the actor's reads alpha detached: either step leaves the
        other's loss as it was."""
        n = self.nets
        policy = n.actor(trunk, generator=self.noise_gen)
        q1, q2 = n.critic.q(n.critic.encoder.projection(trunk), policy.action)
        with full_precision(q1):  # float32 like alpha and log pi; min Q cast up to meet them
            actor_loss = (self.alpha.detach() * policy.log_prob - torch.min(upcast(q1), upcast(q2))).mean()
        # The temperature's loss is float32 throughout: log_alpha is a float32 parameter and log pi
        # comes from the actor's float32 Gaussian.
        alpha_loss = (self.alpha * (-policy.log_prob - self.target_entropy).detach()).mean()
        log_std = policy.log_std
        entropy = 0.5 * log_std.shape[1] * (1.0 + math.log(2 * math.pi)) + log_std.sum(dim=-1)
        return actor_loss, alpha_loss, entropy.detach().mean()

    def step_actor_and_alpha(self, actor_loss: torch.Tensor, alpha_loss: torch.Tensor,
                             entropy: torch.Tensor) -> Metrics:
        """The actor's step, then the temperature's, and their metrics (alpha after its step)."""
        self.run.step(actor_loss, self.actor_opt)
        self.run.step(alpha_loss, self.alpha_opt)
        return {"actor_loss": actor_loss.detach(), "alpha": self.run.read(lambda: self.alpha.detach()),
                "alpha_loss": alpha_loss.detach(), "entropy": entropy}

    def aux_due(self, step: int) -> bool:
        """Whether the auxiliary task trains at agent step ``step``."""
        return self.aux is not None and self.aux.trains and step % self.aux.cfg.update_every == 0

    def update_aux(self, inputs: Inputs, batch: Batch, step: int) -> Metrics:
        """The task's own step, on the RL batch or on a batch of its own (``aux.own_batch``:
        ``inputs["aux_sample"]``, drawn after the RL batch)."""
        if self.aux.cfg.own_batch:
            batch = self.to_batch(inputs["aux_sample"])
        return self.step_aux(batch, step)

    def step_aux(self, batch: Batch, step: int) -> Metrics:
        """One step of the task's optimiser on its objective over ``batch``, then its own
        targets' momentum update (:meth:`AuxiliaryTask.after_step`)."""
        loss = self.run.call(self.aux.objective, batch)
        self.run.step(loss, self.aux.optimizer)
        self.run.read(lambda: self.aux.after_step(step))
        return {"aux_loss": loss.detach()}

    def update_signal(self, batch: Batch, step: int) -> Metrics:
        """One step of the intrinsic signal's own networks, if it trains any (RND's predictor)."""
        if self.signal.optimizer is None:
            return {}
        loss, metrics = self.run.call(self.signal.objective, batch)
        self.run.step(loss, self.signal.optimizer)
        return metrics

    @torch.no_grad()
    def soft_update_targets(self) -> None:
        n, c = self.nets, self.cfg
        ema(n.critic.q.parameters(), n.critic_target.q.parameters(), c.critic_tau)
        ema(n.critic.encoder.parameters(), n.critic_target.encoder.parameters(), c.encoder_tau)

    # -- persistence ------------------------------------------------------------
    def state_dict(self) -> dict:
        state = {
            "nets": self.nets.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            **{key: getattr(self, key).get_state() for key, _ in GENERATORS}, "updates": self.updates,
        }
        if self.aux is not None:
            state["aux"] = self.aux.full_state_dict()
        if self.signal is not None:
            state["signal"] = self.signal.full_state_dict()
        return state

    def load_state_dict(self, state: dict, restore_rng: bool = True) -> None:
        """Load weights, optimisers and (unless ``restore_rng`` is False) random states.

        Evaluation passes ``restore_rng=False``; a checkpoint written on another
        device type (CPU vs CUDA generator states differ) reseeds the generators
        instead, since bit-exact resume across devices is impossible anyway.
        """
        # Optimisers adopt loaded state tensors without copying them; copy so that
        # an in-memory state (e.g. another live agent's) is never shared.
        state = copy.deepcopy(state)
        self.nets.load_state_dict(state["nets"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
        self.updates = state["updates"]
        if restore_rng:
            restore_generators({key: getattr(self, key) for key, _ in GENERATORS}, state, self.updates)
        if self.aux is not None:
            self.aux.load_full_state_dict(state["aux"])
        if self.signal is not None:
            self.signal.load_full_state_dict(state["signal"])
        # A state saved under CUDA graphs holds capturable optimisers; one saved without, not.
        set_capturable(self.optimizers(), self.graphs.record)
        self.graphs.reset()

