"""Seed offsets: every random stream of a run derived from its seed, each defined once.

A run with seed ``s`` seeds its training env, the agent's augmentation generator, the replay sampler and the
seed-phase actions with ``s`` itself; every other stream adds one of the offsets below, chosen so that no two
streams of one run (or of its evaluation and analysis) share a seed. The values are part of every fixed-seed result:
changing one changes the runs.
"""
from __future__ import annotations

NOISE_SEED_OFFSET = 1
"""The agent's policy-noise generator (``noise_gen``, :mod:`imssr.agents.generators`): seed + 1,
apart from its augmentation generator (seed + 0)."""

INTRINSIC_SEED_OFFSET = 2
"""The agent's intrinsic-reward generator (``intrinsic_gen``, the extra views of the signal): seed + 2, so that
computing the intrinsic reward never shifts the base algorithm's streams (beta = 0 is the baseline exactly).
:func:`imssr.analysis.adapter.fix_draws` reseeds it with the same offset."""

TRAINING_EVAL_SEED_OFFSET = 10_000
"""The evaluation envs during training: seed + 10,000, a seed no training env uses."""

EVALUATE_SEED_OFFSET = 20_000
"""``imssr evaluate`` (and :class:`imssr.api.Run`) by default: seed + 20,000, used by no env of
the run's training (seed) nor of its evaluations during training (seed + 10,000)."""

ANALYSIS_ENV_SEED_OFFSET = 30_000
"""``imssr analyze``: the training-scene env that renders the analysed states, analysis seed +
30,000 (apart from every env of training and evaluation)."""

ANALYSIS_ROLLOUT_SEED_OFFSET = 40_000
"""``imssr analyze --source rollouts`` on a run trained in another scene: the env its policy
rolls out in, analysis seed + 40,000."""

ANALYSIS_SCENE_SEED_OFFSET = 50_000
"""``imssr analyze``: the test scene ``i`` (its index in ``--modes``) renders with analysis seed +
50,000 + i, one stream per scene."""


def evaluation_seed(run_seed: int) -> int:
    """Seed of the envs that evaluate a saved run by default (:data:`EVALUATE_SEED_OFFSET`)."""
    return run_seed + EVALUATE_SEED_OFFSET
