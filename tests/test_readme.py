"""The README's code blocks run as written, in order, from a copy of the repository's folder
layout: every block after the quick start (whose two commands CI runs itself: the set-up, then
the test suite) exits 0 and leaves what its comments promise."""
import os
import re
import sys
from pathlib import Path

import pytest

from conftest import REPO, run_command
from imssr.files import read_csv

README = Path(REPO) / "README.md"
QUICK_START = ["bash scripts/setup.sh && .venv/bin/imssr demo --out runs/demo",
               "bash scripts/setup.sh && .venv/bin/python -m pytest -q tests"]


def blocks() -> list[tuple[str, str]]:
    """``(language, code)`` of every fenced block of README.md, in order."""
    return re.findall(r"^```(\w+)\n(.*?)^```$", README.read_text(), flags=re.S | re.M)


def test_the_readme_opens_with_the_two_commands():
    language, code = blocks()[0]
    commands = [line.split("#")[0].strip() for line in code.strip().splitlines()]
    assert (language, commands) == ("bash", QUICK_START)


def test_the_readme_names_no_path_outside_the_repository():
    text = README.read_text()
    assert "../" not in text, "a path outside the repository: the package ships what a user needs"
    for path in re.findall(r"`((?:docs|scripts|imssr|tests|bench)/[\w./-]+)`", text):
        assert (Path(REPO) / path).exists(), path


@pytest.fixture
def folder(tmp_path):
    """An empty working folder laid out as the repository's for the README's commands: its
    ``.venv`` is the environment running the tests."""
    os.symlink(sys.prefix, tmp_path / ".venv")
    return tmp_path


def test_every_readme_block_runs_as_written(folder):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
           # the Python blocks import the checkout's imssr, as `python` in the repository's folder does
           "PYTHONPATH": REPO}
    for language, code in blocks()[1:]:
        if language == "bash":
            run_command("bash", "-euo", "pipefail", "-c", code, cwd=folder, env=env, what=f"README block:\n{code}")
        else:
            assert language == "python", language
            proc = run_command(sys.executable, "-c", code, cwd=folder, env=env, what=f"README block:\n{code}")
            assert "imssr: agent step" not in proc.stdout  # progress=False: no progress lines either
    run = folder / "runs" / "cartpole_swingup" / "im-curl" / "seed_1"
    assert [r["step"] for r in read_csv(run / "eval.csv")] == ["100", "150"]
    assert [r["mode"] for r in read_csv(run / "evaluate.csv")] == ["training", "color_hard", "video_easy"]
    assert (run / "learning_curve.png").stat().st_size > 0
    for algo in ("curl", "im-curl"):
        assert (folder / "runs" / "sweep" / "cartpole_swingup" / algo / "seed_1" / "done.json").exists()
    report = (folder / "runs" / "sweep" / "report")
    assert any(report.iterdir())
    assert read_csv(folder / "runs" / "tiny" / "eval.csv")[-1]["step"] == "120"
    assert not (folder / "runs" / "tiny" / "evaluate.csv").exists()  # Run.evaluate writes nothing
