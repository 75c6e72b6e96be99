"""The notebook API (imssr.train, imssr.load_run, Run): what a loaded run does against the CLI's
evaluation, and its one-line errors (tests/test_readme.py runs the README's example)."""
import os
import re
import sys

import numpy as np
import pytest

import imssr
from imssr.api import _typed
from imssr.errors import ImssrError
from imssr.files import read_csv
from imssr.training.evaluate import evaluate_run

from conftest import tiny_config, tiny_overrides, train_run

@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("api") / "run"
    train_run(tiny_config("im-curl", keep_checkpoints=2), out)
    return out


def test_load_run_picks_checkpoints_as_the_cli_does(tiny_run):
    run = imssr.load_run(str(tiny_run))
    assert (run.step, run.config.algo, run.config.train.steps) == (250, "im-curl", 250)
    assert imssr.load_run(str(tiny_run), checkpoint="125").step == 125
    assert "agent step 250" in repr(run)


def test_act_is_the_trained_agents_deterministic_action(tiny_run):
    run = imssr.load_run(str(tiny_run))
    obs, _ = run.make_env().reset(seed=3)
    assert obs.shape == run.observation_shape
    action = run.act(obs)
    assert action.dtype == np.float32 and np.all(np.abs(action) <= 1)
    np.testing.assert_array_equal(action, run.act(obs))  # deterministic
    other = imssr.load_run(str(tiny_run), checkpoint="125").act(obs)
    assert not np.array_equal(action, other)  # the checkpoint's weights, not fresh ones


def test_evaluate_equals_imssr_evaluate_and_writes_nothing(tiny_run):
    run = imssr.load_run(str(tiny_run))
    result = run.evaluate(mode="color_hard", episodes=2, seed=5)
    assert not os.path.exists(tiny_run / "evaluate.csv")
    evaluate_run(str(tiny_run), episodes=2, modes="color_hard", seed=5, log=lambda _: None)
    row = read_csv(tiny_run / "evaluate.csv")[-1]
    assert float(row["return_mean"]) == pytest.approx(result["return_mean"], abs=1e-5)
    assert len(result["returns"]) == 2 and result["step"] == 250 and result["mode"] == "color_hard"


def test_curves_as_dataframe_and_without_pandas(tiny_run, monkeypatch):
    run = imssr.load_run(str(tiny_run))
    frame = run.curves()
    assert list(frame["step"]) == [125, 250] and "return_mean" in frame
    assert len(run.curves("train")) == len(read_csv(tiny_run / "train.csv"))
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas raises ImportError
    rows = run.curves()
    assert [r["step"] for r in rows] == [125, 250] and rows[0]["mode"] == "training"
    # Typed per column as pandas reads them.
    assert [type(rows[0][k]) for k in ("step", "return_mean", "mode")] == \
        [type(frame[k][0].item()) if k != "mode" else str for k in ("step", "return_mean", "mode")]
    assert _typed([{"a": "1", "b": "0.5", "c": ""}, {"a": "2", "b": "1", "c": "x"}]) == \
        [{"a": 1, "b": 0.5, "c": None}, {"a": 2, "b": 1.0, "c": "x"}]


@pytest.mark.parametrize("call, message", [
    (lambda run: run.act(np.zeros((3, 8, 8), np.uint8)), "act() takes one observation"),
    (lambda run: run.evaluate(episodes=0), "episodes must be a positive integer"),
    (lambda run: run.evaluate(mode="nowhere"), "unknown"),
    (lambda run: run.curves("nope"), "unknown log 'nope'"),
])
def test_bad_input_is_one_line(tiny_run, call, message):
    run = imssr.load_run(str(tiny_run))
    with pytest.raises(ImssrError, match=re.escape(message)) as info:
        call(run)
    assert "\n" not in str(info.value)


def test_load_run_errors(tmp_path, tiny_run):
    with pytest.raises(ImssrError, match="run directory not found"):
        imssr.load_run(str(tmp_path / "missing"))
    with pytest.raises(ImssrError, match="no checkpoint at agent step 7"):
        imssr.load_run(str(tiny_run), checkpoint="7")
    with pytest.raises(ImssrError, match="resume=True needs out"):
        imssr.train(resume=True)


TINY = ["train.seed_steps=20", "train.burst_updates=0", "train.eval_episodes=1", "train.eval_every_steps=20",
        *tiny_overrides(), "train.tensorboard=false"]


def test_train_resumes_to_a_larger_budget(tmp_path):
    out = str(tmp_path / "run")
    run = imssr.train("curl", "cartpole_swingup_sparse", out=out, steps=40, progress=False, overrides=TINY)
    assert run.step == 40
    run = imssr.train(out=out, resume=True, steps=60, progress=False)
    assert run.step == 60 and [r["step"] for r in read_csv(os.path.join(out, "eval.csv"))] == ["20", "40", "60"]


def test_train_seeds_trains_them_in_one_process_as_the_cli_does(tmp_path):
    out = str(tmp_path / "seeds")
    runs = imssr.train("curl", "cartpole_swingup_sparse", out=out, seeds=[3, 5], steps=20, progress=False,
                       overrides=TINY)
    assert [(r.config.train.seed, r.dir, r.step) for r in runs] == [
        (3, os.path.join(out, "seed_3"), 20), (5, os.path.join(out, "seed_5"), 20)]
    with pytest.raises(ImssrError, match="give seed .one run. or seeds .several., not both"):
        imssr.train("curl", "cartpole_swingup_sparse", out=out, seeds=[1], seed=2)
    with pytest.raises(ImssrError, match=r"seeds is a list of different integers, e.g. \[1, 2, 3\], got \[1, 1\]"):
        imssr.train("curl", "cartpole_swingup_sparse", out=out, seeds=[1, 1])


def test_the_api_is_on_the_package():
    from imssr import api

    assert (imssr.train, imssr.load_run, imssr.Run) == (api.train, api.load_run, api.Run)
    with pytest.raises(AttributeError):
        imssr.no_such_name
