"""The rules a run's config must keep: :meth:`RunConfig.validate <imssr.config.RunConfig.validate>`.

Each rule is one line of error naming the field.  The general rules are here, with those of the
intrinsic reward's normalisation and schedule; each plug-in's are beside the plug-in (the
``rules`` of every auxiliary task's and intrinsic signal's ``*_spec.py``), applied here, where the
config is assembled of them.
"""
from __future__ import annotations

import os

from imssr.algos import get_algo
from imssr.auxiliary.registry import AUX_PLUGINS
from imssr.config.overrides import _get, _is_finite, _merged
from imssr.config.schema import FIELD_TYPES
from imssr.config.version import CONFIG_VERSION
from imssr.envs.scenes import get_mode
from imssr.errors import ImssrError
from imssr.intrinsic.registry import SIGNAL_PLUGINS
from imssr.settings import (ADAM_BETA_RULE, BATCH_LAYOUTS, COMPILE_MODES, MAX_ADDRESSABLE_BYTES, MAX_IMAGE_SIZE,
                            MAX_INT, MAX_SEED, MAX_SHADOW_SIZE, MAX_TORCH_THREADS, MIN_CROP_SIZE, NORMALIZATIONS,
                            PRECISIONS, REPLAY_DEVICES, SCHEDULES, SEED_RULE, STACKED_LAYOUTS, TF32_MODES,
                            UPDATE_SCHEDULES, VIDEO_FORMATS, Sections, conv_output_size, type_phrase)


_LEAST = {
    **dict.fromkeys(("env.action_repeat", "env.frame_stack", "agent.encoder_layers", "agent.encoder_filters",
                     "agent.feature_dim", "agent.hidden_dim", "aux.update_every", "intrinsic.decay_every_steps",
                     "train.steps", "train.eval_episodes"), 1),
    **dict.fromkeys(("aux.batch_size", "agent.batch_size", "train.replay_capacity"), 2),
    **dict.fromkeys(("intrinsic.beta0", "intrinsic.norm_eps", "intrinsic.norm_rtol", "train.burst_updates",
                     "train.keep_checkpoints", "train.eval_every_steps", "train.checkpoint_every_steps",
                     "train.eval_video_every"), 0),
}
"""The settings with a lower bound alone, and that bound."""
_CHOICES = {"agent.update_schedule": UPDATE_SCHEDULES, "agent.precision": PRECISIONS, "agent.tf32": TF32_MODES,
            "agent.compile": COMPILE_MODES, "intrinsic.schedule": SCHEDULES, "intrinsic.normalization": NORMALIZATIONS,
            "train.eval_video_format": VIDEO_FORMATS}
"""The settings that take one of a few words, and those words."""


def validate_config(cfg: Sections) -> None:
    """Reject bad values of ``cfg`` (a :class:`~imssr.config.RunConfig`) with one-line errors: the
    general rules here, each plug-in's beside the plug-in (``rules`` of every auxiliary task and
    intrinsic signal)."""
    _check_types(cfg)
    e, a, x, i, t = cfg.env, cfg.agent, cfg.aux, cfg.intrinsic, cfg.train
    checks = [
        (a.compile != "reduce-overhead",
         "agent.compile=reduce-overhead is retired: CUDA graphs of whole agent steps are agent.cuda_graphs=true "
         "(with agent.compile=off or default)"),
        *((_get(cfg, key) >= least, f"{key} must be >= {least}") for key, least in _LEAST.items()),
        *((_get(cfg, key) in choices, f"{key} must be one of {', '.join(choices)}")
          for key, choices in _CHOICES.items()),
        (t.replay_device in REPLAY_DEVICES,
         f"train.replay_device must be one of {', '.join(REPLAY_DEVICES)}, got {t.replay_device!r}"),
        (1 <= e.shadow_size <= MAX_SHADOW_SIZE,
         f"env.shadow_size must be in [1, {MAX_SHADOW_SIZE}] (MuJoCo's default; a larger map sharpens no shadow "
         f"of a frame of at most {MAX_IMAGE_SIZE} px and renders many times slower), got {e.shadow_size}"),
        (0 < a.crop_size <= e.image_size, "agent.crop_size must be in (0, env.image_size]"),
        (a.crop_size >= MIN_CROP_SIZE,
         f"agent.crop_size must be at least {MIN_CROP_SIZE} (the encoder's first convolution is "
         f"{MIN_CROP_SIZE}x{MIN_CROP_SIZE}), got {a.crop_size}"),
        (0 <= a.encoder_head_layers < a.encoder_layers,
         "agent.encoder_head_layers must be in [0, agent.encoder_layers)"),
        (conv_output_size(a.crop_size, a.encoder_layers) >= 1,
         f"agent.encoder_layers={a.encoder_layers} leaves no pixels of a {a.crop_size}px crop"),
        (a.log_std_min < a.log_std_max, "agent.log_std_min must be < agent.log_std_max"),
        (0.0 < a.critic_tau <= 1.0 and 0.0 < a.encoder_tau <= 1.0, "agent taus must be in (0, 1]"),
        (min(a.critic_lr, a.actor_lr, a.alpha_lr, x.lr) > 0, "learning rates must be > 0"),
        *((0.0 <= beta < 1.0, f"agent.{name} must be {ADAM_BETA_RULE}, got {beta}")
          for name, beta in (("critic_beta1", a.critic_beta1), ("actor_beta1", a.actor_beta1),
                             ("alpha_beta1", a.alpha_beta1))),
        (a.init_temperature > 0, "agent.init_temperature must be > 0"),
        (min(a.actor_update_every, a.critic_update_every, a.target_update_every) >= 1,
         "agent update intervals must be >= 1"),
        (0.0 <= a.discount <= 1.0, "agent.discount must be in [0, 1]"),
        (a.update_schedule != "fused" or a.critic_update_every == 1,
         "agent.update_schedule=fused needs agent.critic_update_every=1"),
        # A saved config's stacked layout resumes as the one batch (imssr.config.batching.stacked_layout).
        (a.batch_layout in (*BATCH_LAYOUTS, *STACKED_LAYOUTS),
         f"agent.batch_layout must be one of {', '.join(BATCH_LAYOUTS)}"),
        (i.source in SIGNAL_PLUGINS, f"intrinsic.source must be one of {', '.join(SIGNAL_PLUGINS)}"),
        # Each auxiliary task and signal checks its own settings.
        *(rule for plugin in (*AUX_PLUGINS.values(), *SIGNAL_PLUGINS.values()) for rule in plugin.rules(cfg)),
        (0.0 < i.decay <= 1.0, "intrinsic.decay must be in (0, 1]"),
        (cfg.version == CONFIG_VERSION, f"version must be {CONFIG_VERSION}"),
        (t.seed_steps >= 1, "train.seed_steps must be >= 1 (the first update needs a transition)"),
        (0 <= t.torch_threads <= MAX_TORCH_THREADS,
         f"train.torch_threads must be in [0, {MAX_TORCH_THREADS}] (0: torch's default; OpenMP aborts the "
         f"process when it cannot start a thread, and no CPU runs more at once), got {t.torch_threads}"),
        (0 < t.gpu_share <= 1, f"train.gpu_share must be in (0, 1], got {t.gpu_share}"),
        (bool(t.wandb_project.strip()), "train.wandb_project must not be empty"),
    ]
    for ok, message in checks:
        if not ok:
            raise ImssrError(message)
    check_seed(t.seed)
    _check_upper_bounds(cfg)
    for mode in [e.mode, *t.eval_mode_list(e.mode)]:
        get_mode(mode)
    if e.footage_dir and not os.path.exists(os.path.expanduser(e.footage_dir)):
        raise ImssrError(f"footage not found: {e.footage_dir} (env.footage_dir / --footage)")
    algo = get_algo(cfg.algo)
    if algo.aux != x.name or algo.intrinsic_enabled != i.enabled or \
            (algo.intrinsic_enabled and algo.intrinsic != i.source):
        raise ImssrError(f"algo {cfg.algo} means aux.name={algo.aux}, intrinsic.enabled="
                         f"{str(algo.intrinsic_enabled).lower()}"
                         + (f", intrinsic.source={algo.intrinsic}" if algo.intrinsic_enabled else "")
                         + "; choose the algo instead of overriding these")


def check_seed(seed: int) -> None:
    """A one-line error when ``seed`` is no ``train.seed`` (:data:`SEED_RULE`): what
    :func:`validate_config` checks of it, for configs that differ in the seed alone (a batch
    validates one of them and checks the others' seeds)."""
    if not 0 <= seed <= MAX_SEED:
        raise ImssrError(f"train.seed must be {SEED_RULE}, got {seed}")


def _check_upper_bounds(cfg: Sections) -> None:
    """Integers bounded from above: the replay buffer by what a process can address, the image
    by the renderer, every other integer by :data:`MAX_INT` (layer counts are bounded by the
    crop they must leave pixels of, the shadow map by OpenGL's textures and torch's threads by
    OpenMP, in :func:`validate_config`)."""
    e, t = cfg.env, cfg.train
    frame_bytes = 3 * e.image_size * e.image_size
    if t.replay_capacity > MAX_ADDRESSABLE_BYTES // frame_bytes:
        raise ImssrError(f"train.replay_capacity={t.replay_capacity} needs {t.replay_capacity * frame_bytes:.3g} "
                         f"bytes of {e.image_size}px frames, more than a process can address; "
                         "lower the replay capacity")
    if e.image_size > MAX_IMAGE_SIZE:
        raise ImssrError(f"env.image_size must be at most {MAX_IMAGE_SIZE} (the offscreen framebuffer of the suite's "
                         f"models is 640x{MAX_IMAGE_SIZE}), got {e.image_size}")
    for key, kind in FIELD_TYPES.items():
        if kind is int and key != "train.seed" and _get(cfg, key) > MAX_INT:
            raise ImssrError(f"{key} must be at most {MAX_INT:,}, got {_get(cfg, key)}")


def _check_types(cfg: Sections) -> None:
    """Reject values of the wrong type (e.g. set in code, or from a hand-edited JSON file): a
    value OmegaConf refuses or would have to convert (``"5"`` for an int, ``1`` for a bool), and
    NaN or infinity, which pass every comparison check or break them and end a run only later,
    in a simulator traceback."""
    for key, kind in FIELD_TYPES.items():
        value = _get(cfg, key)
        if kind is float and isinstance(value, (int, float)) and not _is_finite(value):
            raise ImssrError(f"{key} must be a finite number, got {value!r}")
    typed = _merged(cfg, {}, raw={})
    for key, kind in FIELD_TYPES.items():
        value = _get(cfg, key)
        if _get(typed, key) != value or isinstance(value, bool) != (kind is bool):
            raise ImssrError(f"{key} must be {type_phrase(kind)}, got {value!r}")

