"""Pixel SAC with a pluggable auxiliary task and an optional intrinsic reward.

One agent step's update (order as in the CURL / DMC-GB code bases):
  1. critic, every ``critic_update_every`` steps, on ``r + beta_t * r_int``, over
     the observation views the auxiliary task asks for (SVEA: clean + augmented);
  2. actor and temperature, every ``actor_update_every`` steps;
  3. soft update of the target Q heads (``critic_tau``) and target encoder
     (``encoder_tau``), every ``target_update_every`` steps;
  4. the auxiliary task, every ``aux.update_every`` steps;
  5. the intrinsic signal's own networks, if it has any (RND's predictor).
With ``agent.update_schedule = fused`` the actor reuses the critic's encoding of
``o`` and a task that can (CURL, PAD) adds its loss to the critic's in step 1.
The time limit is not terminal: ``discount`` is 0 only for true terminal states.
"""
from __future__ import annotations

import copy
import math
from typing import Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from imssr.augmentations import center_crop, random_crop
from imssr.auxiliary import AuxiliaryTask, Batch, NextObsContext, SharedNetworks, make_aux
from imssr.config import AgentConfig, AuxConfig, IntrinsicConfig
from imssr.intrinsic import IntrinsicReward, IntrinsicSignal, make_signal
from imssr.networks import Actor, ConvTrunk, Critic, Encoder, weight_init
from imssr.replay import FrameReplayBuffer


class SACNetworks(nn.Module):
    """Critic (owning the conv trunk), its target copy, the actor and log alpha."""

    def __init__(self, obs_channels: int, action_dim: int, cfg: AgentConfig):
        super().__init__()
        trunk = ConvTrunk(obs_channels, cfg.crop_size, cfg.encoder_layers, cfg.encoder_filters,
                          cfg.encoder_head_layers, cfg.channels_last, cfg.final_relu)
        self.critic = Critic(Encoder(trunk, cfg.feature_dim, cfg.projection_tanh), action_dim, cfg.hidden_dim)
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
        self.critic_opt = torch.optim.Adam(n.critic.parameters(), lr=cfg.critic_lr,
                                           betas=(cfg.critic_beta1, 0.999))
        # The actor trains its projection and MLP only; the trunk is the critic's.
        self.actor_opt = torch.optim.Adam(n.actor.parameters(), lr=cfg.actor_lr,
                                          betas=(cfg.actor_beta1, 0.999))
        self.alpha_opt = torch.optim.Adam([n.log_alpha], lr=cfg.alpha_lr, betas=(cfg.alpha_beta1, 0.999))
        self.aux: Optional[AuxiliaryTask] = None
        if aux_cfg is not None:
            shared = SharedNetworks(n.critic.encoder, n.critic_target.encoder, action_dim)
            self.aux = make_aux(aux_cfg.name, shared, aux_cfg, cfg).to(self.device)
        self.intrinsic: Optional[IntrinsicReward] = None
        self.signal: Optional[IntrinsicSignal] = None
        if intrinsic_cfg is not None and intrinsic_cfg.enabled:
            self.intrinsic = IntrinsicReward(intrinsic_cfg)
            self.signal = make_signal(intrinsic_cfg, self.obs_shape, cfg, self.aux).to(self.device)
        # Separate generators: augmentations/policy noise, and the intrinsic
        # reward's extra views, so that computing r_int never shifts the
        # random stream of the base algorithm (beta = 0 is the baseline exactly).
        self.gen = torch.Generator().manual_seed(seed)
        self.noise_gen = torch.Generator(device=self.device).manual_seed(seed + 1)
        self.intrinsic_gen = torch.Generator().manual_seed(seed + 2)
        self.updates = 0

    @property
    def alpha(self) -> torch.Tensor:
        return self.nets.log_alpha.exp()

    # -- acting ------------------------------------------------------------------
    @torch.no_grad()
    def act(self, obs: np.ndarray, deterministic: bool) -> np.ndarray:
        """Action in [-1, 1] for one stacked uint8 observation (centre crop)."""
        x = torch.as_tensor(obs, device=self.device).unsqueeze(0)
        x = center_crop(x, self.cfg.crop_size)
        trunk = self.nets.critic.encoder.trunk(x)
        mu, pi, _, _ = self.nets.actor(trunk, generator=self.noise_gen, sample=not deterministic)
        out = mu if deterministic else pi
        return out[0].cpu().numpy().astype(np.float32)

    # -- learning ----------------------------------------------------------------
    def to_batch(self, sample: dict[str, np.ndarray]) -> Batch:
        d = self.device
        raw_obs = torch.as_tensor(sample["obs"], device=d)
        raw_next = torch.as_tensor(sample["next_obs"], device=d)
        size = self.cfg.crop_size
        return Batch(
            obs=random_crop(raw_obs, size, self.gen),
            action=torch.as_tensor(sample["action"], device=d),
            reward=torch.as_tensor(sample["reward"], device=d).unsqueeze(-1),
            discount=torch.as_tensor(sample["discount"], device=d).unsqueeze(-1),
            next_obs=random_crop(raw_next, size, self.gen),
            raw_obs=raw_obs, raw_next_obs=raw_next, generator=self.gen)

    def update(self, replay: FrameReplayBuffer, step: int) -> dict[str, torch.Tensor | float]:
        """All updates of one agent step; ``step`` counts agent steps."""
        c = self.cfg
        fused = c.update_schedule == "fused"
        batch = self.to_batch(replay.sample(c.batch_size))
        metrics: dict[str, torch.Tensor | float] = {}
        aux_due = self.aux is not None and self.aux.trains and step % self.aux.cfg.update_every == 0
        # Fused: the task's loss rides on the critic's encoder pass and backward (only when
        # it trains on the RL batch: a task with a batch of its own needs its own pass).
        fuse_aux = aux_due and self.aux.fuses(c)
        obs_trunk = None
        if step % c.critic_update_every == 0:
            critic_metrics, obs_trunk = self.update_critic(batch, step, fuse_aux)
            metrics.update(critic_metrics)
        if step % c.actor_update_every == 0:
            metrics.update(self.update_actor_and_alpha(batch, obs_trunk if fused else None))
        if step % c.target_update_every == 0:
            self.soft_update_targets()
        if aux_due and not fuse_aux:
            aux_batch = self.to_batch(replay.sample(self.aux.cfg.batch_size)) if self.aux.cfg.own_batch else batch
            metrics.update(self.aux.update(aux_batch, step))
        if self.signal is not None:
            metrics.update(self.signal.update(batch, step))
        self.updates += 1
        return metrics

    def update_critic(self, batch: Batch, step: int, fuse_aux: bool = False
                      ) -> tuple[dict[str, torch.Tensor | float], torch.Tensor]:
        """Critic step (plus the auxiliary step if ``fuse_aux``).

        Returns the metrics and the online trunk's output on ``batch.obs`` from
        before the step, detached (the fused schedule's actor input).
        """
        n, c = self.nets, self.cfg
        metrics: dict[str, torch.Tensor | float] = {}
        views = self.aux.critic_views(batch) if self.aux is not None else [(batch.obs, 1.0)]
        # All views in one forward pass; each is regressed to the same (clean) target.
        obs = views[0][0] if len(views) == 1 else torch.cat([v for v, _ in views])
        encoder_trunk = n.critic.encoder.trunk
        next_features = None
        if fuse_aux and self.aux.fused_next_features:
            # One pass of the shared layers over o and o' (PAD): o' with grad for the task's
            # loss, and detached for the Bellman target's online encoding below.
            both = encoder_trunk.shared_features(torch.cat([obs, batch.next_obs]))
            features, next_features = both[:len(obs)], both[len(obs):]
        else:
            features = encoder_trunk.shared_features(obs)
        trunk = encoder_trunk.head(features).flatten(1)  # = encoder_trunk(obs)
        # Fused: the task's loss from this same pass, computed before the target so that a
        # task whose intrinsic loss is this quantity (PAD) can hand it over.  No generator
        # is shared with the target's, so the order changes no random draw.
        aux_per_sample = self.aux.loss_from_trunk(batch, trunk[:len(batch)], features[:len(batch)],
                                                  next_features) if fuse_aux else None
        with torch.no_grad():
            next_trunk = encoder_trunk(batch.next_obs) if next_features is None \
                else encoder_trunk.head(next_features.detach()).flatten(1)
            _, next_action, next_log_pi, _ = n.actor(next_trunk, generator=self.noise_gen)
            target_latent = n.critic_target.encoder(batch.next_obs)
            tq1, tq2 = n.critic_target.q(target_latent, next_action)
            target_v = torch.min(tq1, tq2) - self.alpha * next_log_pi
            reward = batch.reward
            if self.intrinsic is not None:
                # Algorithm 1: per-sample SSL loss of o', normalised in the batch,
                # r <- r + beta_t * r_int (Eq. 1).
                ctx = NextObsContext(batch.raw_next_obs, batch.next_obs, next_trunk, target_latent,
                                     self.intrinsic_gen, self.intrinsic.cfg.form, batch,
                                     None if aux_per_sample is None else aux_per_sample.detach())
                bonus, stats = self.intrinsic(self.signal(ctx), step, self.signal.label)
                reward = reward + bonus
                metrics.update(stats)
            target_q = reward + batch.discount * c.discount * target_v
        action = batch.action.repeat(len(views), 1)
        q1_all, q2_all = n.critic.q(n.critic.encoder.projection(trunk), action)
        loss = 0.0
        for q1, q2, (_, weight) in zip(q1_all.chunk(len(views)), q2_all.chunk(len(views)), views):
            loss = loss + weight * (F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q))
        total = loss
        if fuse_aux:
            aux_loss = aux_per_sample.mean()
            total = loss + aux_loss
            self.aux.optimizer.zero_grad(set_to_none=True)
            metrics["aux_loss"] = aux_loss.detach()
        self.critic_opt.zero_grad(set_to_none=True)
        total.backward()
        self.critic_opt.step()
        if fuse_aux:
            self.aux.apply_gradients(step)
        metrics.update(critic_loss=loss.detach(), q_mean=q1_all[:len(batch)].detach().mean())
        return metrics, trunk[:len(batch)].detach()

    def update_actor_and_alpha(self, batch: Batch, trunk: Optional[torch.Tensor] = None
                               ) -> dict[str, torch.Tensor]:
        """Actor and temperature step on ``trunk`` (the online encoding of ``batch.obs``).

        Sequential schedule (``trunk`` None): the trunk is recomputed after the
        critic step, as the reference code does, without a graph since the actor
        never trains the convolutions.  Fused: the critic pass's detached encoding.
        """
        n = self.nets
        if trunk is None:
            with torch.no_grad():
                trunk = n.critic.encoder.trunk(batch.obs)
        _, pi, log_pi, log_std = n.actor(trunk, generator=self.noise_gen)
        q1, q2 = n.critic.q(n.critic.encoder.projection(trunk), pi)
        actor_loss = (self.alpha.detach() * log_pi - torch.min(q1, q2)).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.actor_opt.step()
        alpha_loss = (self.alpha * (-log_pi - self.target_entropy).detach()).mean()
        self.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.backward()
        self.alpha_opt.step()
        entropy = 0.5 * log_std.shape[1] * (1.0 + math.log(2 * math.pi)) + log_std.sum(dim=-1)
        return {"actor_loss": actor_loss.detach(), "alpha": self.alpha.detach(),
                "alpha_loss": alpha_loss.detach(), "entropy": entropy.detach().mean()}

    @torch.no_grad()
    def soft_update_targets(self) -> None:
        n, c = self.nets, self.cfg
        _ema(n.critic.q, n.critic_target.q, c.critic_tau)
        _ema(n.critic.encoder, n.critic_target.encoder, c.encoder_tau)

    # -- persistence ------------------------------------------------------------
    def state_dict(self) -> dict:
        state = {
            "nets": self.nets.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "gen": self.gen.get_state(), "noise_gen": self.noise_gen.get_state(),
            "intrinsic_gen": self.intrinsic_gen.get_state(), "updates": self.updates,
        }
        if self.aux is not None:
            state["aux"] = self.aux.full_state_dict()
        if self.signal is not None:
            state["signal"] = self.signal.full_state_dict()
        return state

    def load_state_dict(self, state: dict, restore_rng: bool = True) -> None:
        """Load weights, optimisers and (unless ``restore_rng`` is False) random states.

        Evaluation passes ``restore_rng=False``; a checkpoint written on another
        device type (CPU vs CUDA generator states differ) reseeds the policy-noise
        generator instead, since bit-exact resume across devices is impossible anyway.
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
            self.gen.set_state(state["gen"])
            self.intrinsic_gen.set_state(state["intrinsic_gen"])
            try:
                self.noise_gen.set_state(state["noise_gen"])
            except RuntimeError:  # saved on another device type
                self.noise_gen.manual_seed(int(self.gen.initial_seed()) + 1 + self.updates)
        if self.aux is not None:
            self.aux.load_full_state_dict(state["aux"])
        if self.signal is not None:
            self.signal.load_full_state_dict(state["signal"])


def _ema(src: nn.Module, dst: nn.Module, tau: float) -> None:
    for p, tp in zip(src.parameters(), dst.parameters()):
        tp.data.lerp_(p.data, tau)
