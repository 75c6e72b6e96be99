"""``python -m imssr.gpucheck``: the CPU smoke run of the GPU machine's one command (tiny
networks and budgets; its figures mean nothing), and the report it writes."""
import torch

from imssr import gpucheck
from imssr.agents import build


def test_the_gpu_check_runs_every_item_and_writes_one_report(monkeypatch, tmp_path, capsys):
    # Dynamo's eager backend: the same capture as inductor, without minutes of C++ compilation.
    compile_ = build.compile_networks
    monkeypatch.setattr(build, "compile_networks", lambda nets, mode, backend="inductor": compile_(nets, mode, "eager"))
    out = tmp_path / "gpucheck.md"
    status = gpucheck.main(["--tiny", "--device", "cpu", "--out", str(out), "--bases", "curl",
                            "--compile-modes", "default", "--skip", "bench"])
    report = out.read_text()
    assert status == 0, report
    assert report.startswith("# imssr GPU check\n") and f"torch {torch.__version__}" in report
    assert "all items passed or were skipped" in report
    rows = [line for line in report.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r.split("|")[1].strip() for r in rows] == [
        "CUDA tests (pytest -k cuda)", "train curl fp32, 8 steps", "train curl bf16, 8 steps",
        "train curl fp32 agent.compile=default, 4 steps", "train curl fp32 agent.cuda_graphs=true, 4 steps"]
    assert [r.split("|")[2].strip() for r in rows] == ["skipped", "pass", "pass", "pass", "pass"]
    assert all(float(r.split("|")[3]) > 0 for r in rows[1:])  # steps/s of each training


def test_a_failing_item_is_reported_and_the_others_go_on(tmp_path):
    item = gpucheck.run_item(gpucheck.Item("broken"), lambda: 1 / 0, torch.device("cpu"))
    assert item.ok is False and item.note == "ZeroDivisionError: division by zero"
    assert item.row().startswith("| broken | FAIL |")


def test_bad_arguments_are_one_line_errors(tmp_path, capsys):
    """A bad base, a CUDA device without CUDA or a budget of 0 is refused in one line, exit 2,
    before any item runs and without a report."""
    out = tmp_path / "gpucheck.md"
    cases = [(["--bases", "curl,nope"], "unknown algo 'nope'"),
             (["--steps", "0"], "argument --steps: expects a positive integer, got '0'"),
             (["--compile-steps", "x"], "argument --compile-steps: expects a positive integer, got 'x'"),
             (["--skip", "tset"], "unknown item 'tset' in --skip; choose from tests, train, compile, bench"),
             (["--bogus"], "unrecognized arguments: --bogus")]
    if not torch.cuda.is_available():
        cases.append((["--device", "cuda"], "device 'cuda' requested but CUDA is not available; use --device cpu"))
    for argv, message in cases:
        assert gpucheck.main(["--tiny", "--device", "cpu", "--out", str(out), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"imssr: error: {message}"), (argv, err)
        assert not out.exists()


def test_a_hung_subprocess_fails_its_item(monkeypatch):
    """The CUDA tests and the bench run under a timeout; running past it fails that item only."""
    def hang(*args, timeout=None, **kwargs):
        assert timeout == gpucheck.SUBPROCESS_TIMEOUT_S
        raise gpucheck.subprocess.TimeoutExpired(args[0], timeout)

    monkeypatch.setattr(gpucheck.subprocess, "run", hang)
    item = gpucheck.bench(torch.device("cpu"), "--steps 1", gpucheck.Item("bench"))
    assert item.ok is False
    assert item.note == f"RuntimeError: bench/gpu.py timed out after {gpucheck.SUBPROCESS_TIMEOUT_S} s"
