"""The numbers the results' pages quote are held by the committed files they name: the runs' CSV
logs and the machine's logs under docs/results/, read here as a reader would check them."""
import csv
import glob
import os
import re

from conftest import REPO
from imssr.report.stats import MIN_SEEDS_FOR_BOOTSTRAP

RESULTS = os.path.join(REPO, "docs", "results")
DMC = os.path.join(RESULTS, "dmc100k_cartpole_swingup")
FP32_LOG = os.path.join(DMC, "gpu_log", "fp32")


def _text(path: str) -> str:
    """A page's text with its line breaks and runs of spaces as single spaces (prose is reflowed)."""
    with open(path, encoding="utf-8") as fh:
        return " ".join(fh.read().split())


def _rows(path: str) -> list[dict]:
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def _runs(precision: str) -> dict[tuple[str, int], str]:
    """``(algo, seed) -> run directory`` of the committed DMC-100k runs of one precision."""
    found = glob.glob(os.path.join(DMC, "runs", precision, "cartpole_swingup", "*", "seed_*"))
    assert len(found) == 6, found
    return {(os.path.basename(os.path.dirname(d)), int(d.rsplit("_", 1)[1])): d for d in found}


def _evaluations(run: str) -> dict[int, float]:
    return {int(r["step"]): float(r["return_mean"]) for r in _rows(os.path.join(run, "eval.csv"))}


def _seconds(log: str, what: str) -> int:
    """The ``N`` of "``what`` at N s" in a machine log."""
    with open(log, encoding="utf-8") as fh:
        return int(re.search(rf"{what} at (\d+) s", fh.read()).group(1))


def _run_seconds(sweep_log: str) -> list[int]:
    """Each run's seconds in a sweep's log ("done ... , 482s")."""
    with open(sweep_log, encoding="utf-8") as fh:
        return [int(s) for s in re.findall(r"^done .*, (\d+)s$", fh.read(), re.M)]


def test_the_dmc100k_page_says_of_its_stopped_sweep_what_the_logs_hold():
    """Where the fp32 sweep stopped (each run's train.csv: the last row before the pause its stop
    made), how long its two calls took (the machine's logs) and how fast the runs went
    (eval.csv's wall clock), as docs/results/dmc100k_cartpole_swingup/README.md quotes them."""
    text = _text(os.path.join(DMC, "README.md"))
    last_before, pauses = [], []
    for run in _runs("fp32").values():
        rows = _rows(os.path.join(run, "train.csv"))
        pause, step = max((float(b["wall_time"]) - float(a["wall_time"]), int(a["step"])) for a, b in zip(rows, rows[1:]))
        last_before.append(step)
        pauses.append(pause)
    assert f"those rows are of agent steps {min(last_before):,} to {max(last_before):,}" in text
    assert f"came {round(min(pauses))}-{round(max(pauses))} s later, after the resume" in text

    call1, call2 = (os.path.join(FP32_LOG, f"call{n}_machine.txt") for n in (1, 2))
    setup1, stop, end1 = (_seconds(call1, w) for w in ("setup done", "deadline", "sweep ended"))
    setup2, end2 = (_seconds(call2, w) for w in ("setup done", "sweep ended"))
    assert f"stopped (SIGTERM) at {stop} s of the machine's first call, {stop - setup1} s after the sweep began" \
           in text and f"setup done at {setup1} s" in text
    assert f"took {end1 - setup1} + {end2 - setup2} s of sweep over the machine's two calls" in text
    assert f"from the end of setup, at {setup1} and {setup2} s, to the sweep's end, at {end1} and {end2} s" in text
    resumed = _run_seconds(os.path.join(FP32_LOG, "call2_sweep.log"))
    assert f"finished them {min(resumed)}-{max(resumed)} s later" in text
    bf16 = _run_seconds(os.path.join(DMC, "gpu_log", "bf16", "sweep.log"))
    assert f"({min(bf16)}-{max(bf16)} s a run, `gpu_log/bf16/sweep.log`)" in text
    assert f"took {min(bf16)}-{max(bf16)} s (`gpu_log/bf16/`)" in text

    def rates(precision):
        out = []
        for run in _runs(precision).values():
            wall = {int(r["step"]): float(r["wall_time"]) for r in _rows(os.path.join(run, "eval.csv"))}
            out.append(8750 / (wall[10000] - wall[1250]))
        return out

    fp32 = rates("fp32")
    assert f"**{min(fp32):.1f}-{max(fp32):.1f} agent steps per second**" in text
    assert f"about {sum(fp32):.0f} for the six together" in text
    bf16_rates = rates("bf16")
    assert f"advanced at {min(bf16_rates):.1f}-{max(bf16_rates):.1f} agent steps per second each" in text


def test_performance_history_quotes_the_dmc100k_evaluations_as_they_are():
    """The "band" of evaluations between agent steps 2,500 and 7,500 that
    docs/results/performance_history.md reads in the DMC-100k runs, and its projection."""
    text = _text(os.path.join(RESULTS, "performance_history.md"))
    ev = {run: _evaluations(d) for run, d in _runs("fp32").items()}
    band = range(2500, 7501, 1250)

    steady = [ev[run][s] for run in (("curl", 1), ("im-curl", 1), ("im-curl", 3)) for s in band]
    assert f"CURL seed 1 and IM-CURL seeds 1 and 3 all five ({round(min(steady))}-{round(max(steady))})" in text
    assert min(steady) >= 200
    curl2, im2, curl3 = ev["curl", 2], ev["im-curl", 2], ev["curl", 3]
    after = [curl2[s] for s in band if s > 2500]
    assert f"CURL seed 2 all but its {curl2[2500]:.1f} at 2,500 ({round(min(after))}-{round(max(after))} after it)" \
           in text
    after = [im2[s] for s in band if s > 3750]
    assert f"IM-CURL seed 2 all but its {im2[3750]:.1f} at 3,750 ({round(im2[2500])} before it, " \
           f"{round(min(after))}-{round(max(after))} after)" in text
    for name, run, steps in (("CURL seed 1", ("curl", 1), (3750, 5000)), ("CURL seed 2", ("curl", 2), (5000, 6250)),
                             ("IM-CURL seed 1", ("im-curl", 1), (3750, 5000, 6250))):
        values = " -> ".join(str(round(ev[run][s])) for s in steps)
        assert f"{name} {values} (" in text, (name, values)
    assert f"{round(im2[2500])} -> {round(im2[3750])} (2,500 -> 3,750)" in text
    assert f"CURL seed 3, passed through the band ({round(curl3[3750])} at 3,750, {round(curl3[5000])} at 5,000) " \
           f"and climbed on, to {curl3[6250]:.1f} at 6,250 and {curl3[7500]:.1f} at 7,500" in text
    assert curl3[6250] > 300 and curl3[7500] > 300
    final = [e[12500] for e in ev.values()]
    assert f"All six climbed by 12,500 agent steps, to {round(min(final))}-{round(max(final))}" in text
    assert f"would have needed about {round(250_000 / 113 / 60)} minutes at 113 agent steps/s (250,000 / 113 s: a " \
           "projection, not a measurement)" in text


def test_no_committed_report_reads_spread_from_too_few_seeds_unless_marked_superseded():
    """A committed report.md with an IQM or bootstrap interval from fewer than 5 runs, or the
    population std, is not what today's `imssr report` writes: it says at its top that it is
    superseded."""
    found = glob.glob(os.path.join(RESULTS, "**", "report.md"), recursive=True)
    assert found
    for path in found:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
        runs = [int(n) for n in re.findall(r"^\| `[^`]+` \| [\d.]+T \| (?:IQM|P\(X > Y\)) \|.* \| (\d+) \|$",
                                           text, re.M)]
        stale = any(n < MIN_SEEDS_FOR_BOOTSTRAP for n in runs) or "(ddof 0)" in text
        assert not stale or text.startswith("> **Superseded:**"), path
