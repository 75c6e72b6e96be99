"""bench/gpu.py: its table's structure on a tiny CPU smoke run and its arithmetic (never timings),
and the one-line error when CUDA is asked for and absent."""
import csv
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from conftest import TINY_NETWORKS, load_script, tiny_sets

ROOT = Path(__file__).resolve().parent.parent
GPU_BENCH = ROOT / "bench" / "gpu.py"
TINY = ["--batch", "8", "--steps", "2", "--warmup", "1", "--seed-steps", "20", "--threads", "1",
        *tiny_sets(TINY_NETWORKS)]


def run_bench(*args):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(GPU_BENCH), *args], capture_output=True, text=True,
                          env=env, cwd=ROOT)


def table_rows(stdout: str) -> list[list[str]]:
    """The Markdown table's body rows, as cells."""
    lines = [line for line in stdout.splitlines() if line.startswith("| ")]
    assert lines and lines[1].startswith("| ---"), stdout
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]


def load_gpu_bench():
    return load_script("bench/gpu.py")


def test_cpu_smoke_run_prints_one_row_per_algo_and_variant_with_the_baseline_first(tmp_path):
    out = tmp_path / "bench.csv"
    # Eager variants only: torch.compile takes minutes on these cores.  bf16/off alone: the
    # fp32 eager baseline of the ratios is measured without being asked for.
    proc = run_bench("--device", "cpu", "--algos", "curl", "soda", "--variants", "bf16/off",
                     "--csv", str(out), *TINY)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    header = next(line for line in proc.stdout.splitlines() if line.startswith("| algo"))
    assert "hours for 500,000 steps" in header and "warm-up s" in header and "peak GiB" in header
    rows = table_rows(proc.stdout)
    assert [r[:3] for r in rows] == [["curl", "fp32", "off"], ["curl", "bf16", "off"],
                                     ["soda", "fp32", "off"], ["soda", "bf16", "off"]]
    for algo, precision, mode, rate, median_ms, ratio, hours, warmup, peak in rows:
        assert float(rate) > 0 and float(median_ms) > 0 and float(warmup) >= 0
        assert float(ratio) == 1.0 if precision == "fp32" else float(ratio) > 0
        # hours = T / (steps/s) / 3600, both printed rounded
        assert float(hours) == pytest.approx(500_000 / float(rate) / 3600, rel=0.02, abs=0.06)
        assert peak == "n/a (cpu)"
    assert "excludes evaluation" in proc.stdout and "excluded from steps/s" in proc.stdout
    assert proc.stdout.splitlines()[0].startswith("device: CPU")
    # The variants sample from the store training would use here: the host's.
    assert "replay store, resolved as training would: train.replay_device=auto: host (numpy frames" \
        in proc.stdout
    with open(out, newline="") as f:
        written = list(csv.DictReader(f))
    assert [[r["algo"], r["precision"], r["compile"], r["steps/s"]] for r in written] == \
        [r[:4] for r in rows]
    assert {r["total_steps"] for r in written} == {"500000"}


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is present")
def test_cuda_absent_is_one_line_that_points_to_the_cpu_smoke_run():
    proc = run_bench("--device", "cuda")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stdout == ""
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "CUDA is not available" in proc.stderr and "--device cpu" in proc.stderr


def test_bad_variant_is_one_line():
    proc = run_bench("--device", "cpu", "--variants", "fp16/off")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "PRECISION/COMPILE" in proc.stderr


def test_rows_ratio_hours_and_failed_variants():
    gpu = load_gpu_bench()

    def variant(algo, precision, mode, times, error=None, warmup=(3.0,), peak=2**30):
        return SimpleNamespace(algo=algo, precision=precision, mode=mode, times=list(times), error=error,
                               warmup_times=list(warmup), peak=peak)

    table = gpu.rows([variant("curl", "fp32", "off", [0.1, 0.1]),
                      variant("curl", "bf16", "off+graphs", [0.05, 0.05], warmup=(40.0, 2.0)),
                      variant("soda", "fp32", "off", [], error="RuntimeError: boom"),
                      variant("soda", "bf16", "off", [0.2])], total_steps=36_000, cuda=True)
    assert table[0]["steps/s"] == "10.00" and table[0]["x fp32 eager"] == "1.00"
    assert table[0]["hours for T"] == "1.0" and table[0]["peak GiB"] == "1.00"
    assert table[1]["x fp32 eager"] == "2.00" and table[1]["hours for T"] == "0.5"
    assert table[1]["warm-up s"] == "42.0"
    assert table[2]["steps/s"] == "failed: RuntimeError: boom" and table[2]["hours for T"] == ""
    # no baseline for soda (it failed): no ratio, the rest stands
    assert table[3]["x fp32 eager"] == "" and table[3]["steps/s"] == "5.00"
    md = gpu.markdown(table, 36_000).splitlines()
    assert md[0].startswith("| algo |") and "hours for 36,000 steps" in md[0]
    assert len(md) == 2 + 4 and all(line.count("|") == len(gpu.COLUMNS) + 1 for line in md)
