"""``python -m imssr.gpucheck``: the CPU smoke run of the GPU machine's one command (tiny
networks and budgets; its figures mean nothing), and the report it writes."""
import torch

from imssr import gpucheck
from imssr.agents import SACAgent


def test_the_gpu_check_runs_every_item_and_writes_one_report(monkeypatch, tmp_path, capsys):
    # Dynamo's eager backend: the same capture as inductor, without minutes of C++ compilation.
    compile_ = SACAgent._compile
    monkeypatch.setattr(SACAgent, "_compile", lambda self, mode, backend="inductor": compile_(self, mode, "eager"))
    out = tmp_path / "gpucheck.md"
    status = gpucheck.main(["--tiny", "--device", "cpu", "--out", str(out), "--bases", "curl",
                            "--compile-modes", "reduce-overhead", "--skip", "bench"])
    report = out.read_text()
    assert status == 0, report
    assert report.startswith("# imssr GPU check\n") and f"torch {torch.__version__}" in report
    assert "all items passed or were skipped" in report
    rows = [line for line in report.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r.split("|")[1].strip() for r in rows] == [
        "CUDA tests (pytest -k cuda)", "train curl fp32, 8 steps", "train curl bf16, 8 steps",
        "train curl fp32 agent.compile=reduce-overhead, 4 steps"]
    assert [r.split("|")[2].strip() for r in rows] == ["skipped", "pass", "pass", "pass"]
    assert all(float(r.split("|")[3]) > 0 for r in rows[1:])  # steps/s of each training


def test_a_failing_item_is_reported_and_the_others_go_on(tmp_path):
    item = gpucheck.run_item(gpucheck.Item("broken"), lambda: 1 / 0, torch.device("cpu"))
    assert item.ok is False and item.note == "ZeroDivisionError: division by zero"
    assert item.row().startswith("| broken | FAIL |")
