"""A plug-in owns its settings: a new auxiliary task is its two modules and one registry line.

The toy task below is added to a copy of the package exactly as docs/architecture.md ("Writing a
new auxiliary task") says, and nothing else of the copy is edited: its algorithms, preset,
settings, rules and a real training run must all follow.
"""
import os
import shutil
import subprocess
import sys
import textwrap

import pytest

from conftest import REPO, tiny_sets
from imssr.auxiliary import AUX_PLUGINS
from imssr.config import FIELD_TYPES, field_docs
from imssr.intrinsic import SIGNAL_PLUGINS
from imssr.settings import dataclass_field_docs

TOY_SPEC = '''
"""Toy: a predictor head regressing the target encoder's latent (a test's plug-in)."""
from __future__ import annotations

from dataclasses import dataclass

from imssr.settings import TABLE3, AuxPlugin, Sections, Setting


@dataclass
class ToySettings:
    toy_weight: float = 1.0
    """Toy: weight of the toy loss."""


def rules(cfg: Sections) -> list[tuple[bool, str]]:
    return [(cfg.aux.toy_weight > 0, "aux.toy_weight must be > 0")]


PLUGIN = AuxPlugin(
    name="toy", label="TOY", implementation="Toy", description="SAC + a toy task",
    settings=ToySettings, rules=rules,
    preset=(Setting("agent.encoder_layers", 4, TABLE3), Setting("agent.encoder_head_layers", 0, TABLE3),
            Setting("aux.lr", 1e-3, "test"),
            Setting("aux.update_every", 1, "test"), Setting("aux.own_batch", False, "test"),
            Setting("aux.batch_size", 128, "test"), Setting("aux.toy_weight", 2.0, "test", "the toy's own"),
            Setting("train.replay_capacity", 100_000, TABLE3)),
)
'''

TOY_TASK = '''
"""Toy: a predictor head regressing the target encoder's latent."""
import torch
from torch import nn

from imssr.auxiliary.base import AuxiliaryTask


class Toy(AuxiliaryTask):
    name = "toy"

    def __init__(self, shared, cfg, agent_cfg):
        super().__init__(shared, cfg, agent_cfg)
        self.head = nn.Linear(agent_cfg.feature_dim, agent_cfg.feature_dim)

    def shared_parameters(self):
        return list(self.shared.encoder.parameters())

    def _loss(self, obs):
        with torch.no_grad():
            target = self.shared.target_encoder(obs)
        return self.cfg.toy_weight * (self.head(self.shared.encoder(obs)) - target).pow(2).mean(dim=1)

    def per_sample_loss(self, batch, enc=None):
        return self._loss(batch.obs)

    @torch.no_grad()
    def intrinsic_loss(self, ctx):
        return self._loss(ctx.batch.next_obs)
'''

# One episode (125 agent steps at cartpole's action repeat 8) and one evaluation.
TINY = ["--steps", "125", "--seed-steps", "60", "--eval-every", "125", "--eval-episodes", "1",
        "--replay-capacity", "500", "--no-progress", *tiny_sets(), "--set", "train.burst_updates=0"]


@pytest.fixture(scope="module")
def with_toy(tmp_path_factory):
    """A copy of the package with the toy task added: two files and one registry line."""
    root = tmp_path_factory.mktemp("toy")
    package = root / "imssr"
    shutil.copytree(os.path.join(REPO, "imssr"), package, ignore=shutil.ignore_patterns("__pycache__"))
    (package / "auxiliary" / "toy_spec.py").write_text(TOY_SPEC)
    (package / "auxiliary" / "toy.py").write_text(TOY_TASK)
    registry = package / "auxiliary" / "registry.py"
    before = registry.read_text().splitlines()
    after = [line.replace('"pad", "svea")', '"pad", "svea", "toy")') for line in before]
    assert sum(a != b for a, b in zip(before, after)) == 1, "the registry line moved: update this test"
    registry.write_text("\n".join(after) + "\n")
    return root


def run_with(root, *argv, code=None):
    env = {**os.environ, "PYTHONPATH": str(root), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    args = ["-c", code] if code else ["-m", "imssr", *argv]
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env, cwd=root, timeout=600)


def test_the_toy_task_makes_its_algorithms_preset_and_settings(with_toy):
    proc = run_with(with_toy, "algos")
    assert proc.returncode == 0, proc.stderr
    assert all(name in proc.stdout for name in ("toy ", "im-toy", "toy+rnd", "toy+re3", "SAC + a toy task"))
    proc = run_with(with_toy, "config", "--algo", "im-toy", "--task", "walker_walk", "--explain")
    assert proc.returncode == 0, proc.stderr
    assert "| `aux.toy_weight` | `2.0` | test | the toy's own |" in proc.stdout
    assert "| `intrinsic.beta0` | `0.01` | imssr |" in proc.stdout  # no Table V row: imssr's default
    proc = run_with(with_toy, code=textwrap.dedent("""
        import os, sys
        import imssr
        from imssr.config import FIELD_TYPES, field_docs
        from imssr.presets import make_config, run_config
        from imssr.errors import ImssrError
        assert imssr.__file__.startswith(os.getcwd()), imssr.__file__  # the copy, not the repository
        assert FIELD_TYPES["aux.toy_weight"] is float
        assert field_docs()["aux.toy_weight"] == "Toy: weight of the toy loss."
        assert make_config("im-toy", "walker_walk").aux.toy_weight == 2.0
        assert make_config("curl", "walker_walk").aux.toy_weight == 1.0  # every config carries it
        assert run_config("toy", "walker_walk", overrides=["aux.toy_weight=3"]).aux.toy_weight == 3.0
        try:
            run_config("toy", "walker_walk", overrides=["aux.toy_weight=-1"])
        except ImssrError as exc:
            print(exc)
        assert "torch" not in sys.modules
    """))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "aux.toy_weight must be > 0"


def test_the_toy_task_trains_and_evaluates(with_toy):
    out = with_toy / "run"
    proc = run_with(with_toy, "train", "--algo", "im-toy", "--task", "cartpole_swingup", "--seed", "1", "--out",
                    str(out), *TINY, "--set", "aux.toy_weight=0.5")
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    with open(out / "train.csv") as fh:
        header, *rows = fh.read().splitlines()
    columns = header.split(",")
    assert rows and float(rows[-1].split(",")[columns.index("aux_loss")]) > 0
    assert float(rows[-1].split(",")[columns.index("beta")]) > 0
    # The saved config reads back in the copy, with the toy's setting.
    proc = run_with(with_toy, code=f"import imssr; r = imssr.load_run({str(out)!r}); print(r.config.aux.toy_weight)")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "0.5"
    proc = run_with(with_toy, "evaluate", "--run", str(out), "--episodes", "1")
    assert proc.returncode == 0 and "return" in proc.stdout, proc.stderr


def test_every_plugin_declares_documented_settings_of_its_own():
    owners = {}
    for plugin in (*AUX_PLUGINS.values(), *SIGNAL_PLUGINS.values()):
        assert plugin.implementation_class().name == plugin.name
        fields = dataclass_field_docs(plugin.settings) if plugin.settings else {}
        section = "aux" if plugin.name in AUX_PLUGINS else "intrinsic"
        for name in fields:
            assert f"{section}.{name}" in FIELD_TYPES and field_docs()[f"{section}.{name}"] == fields[name]
            owners.setdefault(name, plugin.name)
        if plugin.settings:
            assert set(fields) == set(plugin.settings.__dataclass_fields__), f"{plugin.name}: a field without a docstring"
        for row in plugin.preset:
            assert row.field in FIELD_TYPES, f"{plugin.name}'s preset sets unknown {row.field}"
    assert owners == {"tau": "soda", "overlay_alpha": "soda", "image_dir": "soda", "image_pool_size": "soda",
                      "svea_alpha": "svea", "svea_beta": "svea", "form": "ssl", "rnd_lr": "rnd", "rnd_dim": "rnd",
                      "re3_k": "re3", "re3_dim": "re3"}


def test_two_plugins_may_not_declare_one_field():
    from dataclasses import dataclass

    from imssr.settings import AuxCore, AuxPlugin, compose_section

    @dataclass
    class Clash:
        lr: float = 1.0
        """Clashes with the core's."""

    plugin = AuxPlugin(name="clash", implementation="Clash", label="C", description="", settings=Clash)
    with pytest.raises(TypeError, match="AuxConfig.lr is declared by both AuxCore and clash"):
        compose_section("AuxConfig", AuxCore, [plugin], __name__, "")


def test_an_unregistered_plugin_names_what_it_lacks():
    from imssr.auxiliary.soda_spec import PLUGIN

    assert AUX_PLUGINS["soda"].implementation_class().__name__ == "SODA"
    with pytest.raises(TypeError, match="the plug-in 'soda' is not registered"):
        PLUGIN.implementation_class()
