"""The built wheel on its own: installed into a fresh virtual environment in a temporary folder,
away from the checkout and from ``../shared``, it carries the published numbers and a report
prints them (no code path reads files beside the repository)."""
import os
import shutil
import site
import subprocess
import sys
import zipfile

from conftest import REPO, curve, make_run


def _build_wheel(tmp_path) -> str:
    """The wheel of a copy of the package's sources (the build leaves nothing in the checkout)."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(os.path.join(REPO, name), src)
    shutil.copytree(os.path.join(REPO, "imssr"), src / "imssr",
                    ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index",
                    "-q", "-w", str(tmp_path / "dist"), str(src)], check=True, capture_output=True, text=True)
    (wheel,) = os.listdir(tmp_path / "dist")
    return str(tmp_path / "dist" / wheel)


def test_a_wheel_installed_elsewhere_prints_the_papers_numbers(tmp_path):
    wheel = _build_wheel(tmp_path)
    assert "imssr/report/data/imssr_paper.csv" in zipfile.ZipFile(wheel).namelist()
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = str(venv / "bin" / "python")
    target = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                            check=True, capture_output=True, text=True).stdout.strip()
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--target", target,
                    wheel], check=True)
    # imssr's dependencies from this environment, after the new one's own site-packages: the
    # wheel's imssr comes first, and this checkout's editable install is not activated (a path
    # in a .pth file is added as it is; the .pth files inside it are not read).
    with open(os.path.join(target, "deps.pth"), "w") as fh:
        fh.write("\n".join(site.getsitepackages()) + "\n")
    runs, report = tmp_path / "elsewhere" / "runs", tmp_path / "elsewhere" / "report"
    for seed in (1, 2):
        make_run(str(runs), "curl", seed, curve(0, 0, 700.0 + seed))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([python, "-c", "import imssr, sys; print(imssr.__file__)"], cwd=tmp_path / "elsewhere",
                          capture_output=True, text=True, env=env)
    assert proc.stdout.strip().startswith(target), proc.stdout + proc.stderr
    proc = subprocess.run([python, "-m", "imssr", "report", str(runs), "--out", str(report), "--reps", "20"],
                          cwd=tmp_path / "elsewhere", capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    md = (report / "report.md").read_text()
    assert "paper 1.0T" in md and "744.2 ± 23.8 (n = 5)" in md


def _requirements() -> list[str]:
    """Every requirement of pyproject.toml: the dependencies and each extra's."""
    import tomllib

    with open(os.path.join(REPO, "pyproject.toml"), "rb") as fh:
        project = tomllib.load(fh)["project"]
    return project["dependencies"] + [r for extra in project["optional-dependencies"].values() for r in extra]


def _lock() -> dict[str, str]:
    """constraints.txt: each package's normalised name -> its line."""
    import re

    with open(os.path.join(REPO, "constraints.txt")) as fh:
        return {re.split(r"[=<>]", line)[0].strip().lower().replace("_", "-"): line.strip()
                for line in fh if line.strip() and not line.startswith("#")}


def test_the_package_states_ranges_and_the_lock_pins_them():
    import re
    import tomllib

    with open(os.path.join(REPO, "pyproject.toml"), "rb") as fh:
        project = tomllib.load(fh)["project"]
    from packaging.requirements import Requirement

    requirements = _requirements()
    exact = [r for r in requirements if any(s.operator == "==" for s in Requirement(r).specifier)]
    assert not exact, "exact versions belong in constraints.txt"
    assert project["optional-dependencies"]["all"] == ["imssr[sweep,report,wandb,slurm]"]
    pinned = _lock()
    assert all("==" in line for line in pinned.values())
    for requirement in requirements:
        name = re.split(r"[\[=<>!~ ;]", requirement)[0].lower().replace("_", "-")
        assert name == "imssr" or name in pinned, f"{name} has no exact version in constraints.txt"
    text = open(os.path.join(REPO, "pyproject.toml")).read()
    assert "development machine" not in text


def test_the_lock_pins_versions_a_public_index_serves_within_the_ranges():
    """No local version label (``+cpu``, ``+cu130``): PyPI serves none, so such a pin fails to
    resolve anywhere without the wheel folder it came from; and each pin lies in pyproject's range."""
    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name
    from packaging.version import Version

    pins = {canonicalize_name(name): Version(line.split("==", 1)[1]) for name, line in _lock().items()}
    assert not {name: str(v) for name, v in pins.items() if v.local}, "local version labels in constraints.txt"
    for line in _requirements():
        req = Requirement(line)
        if req.name != "imssr":
            assert req.specifier.contains(pins[canonicalize_name(req.name)], prereleases=True), \
                f"constraints.txt pins {req.name} {pins[canonicalize_name(req.name)]}, outside {line!r}"


def test_an_upper_bound_stands_only_with_the_break_written_beside_it():
    """A cap downgrades a user's newer package: pyproject.toml caps a requirement only where the
    comment just above names the release that breaks imssr."""
    import re

    lines = open(os.path.join(REPO, "pyproject.toml")).read().splitlines()
    project = lines[lines.index("[project]"):lines.index("[project.scripts]")]
    for i, line in enumerate(project):
        for requirement in re.findall(r'"([A-Za-z0-9_.\-\[\]]+[<>=!~][^"]*)"', line):
            if "<" not in requirement:
                continue
            above = []
            for prev in reversed(project[:i]):
                if not prev.strip().startswith("#"):
                    break
                above.insert(0, prev)
            assert "break" in " ".join(above), f"{requirement!r} is capped without the break written above it"


def test_the_torch_lower_bound_is_the_oldest_torch_imssr_has_run_on():
    import re

    from packaging.requirements import Requirement
    from packaging.version import Version

    (torch,) = [Requirement(r) for r in _requirements() if Requirement(r).name == "torch"]
    (lower,) = [Version(s.version) for s in torch.specifier if s.operator == ">="]
    readme = " ".join(open(os.path.join(REPO, "docs", "usage.md")).read().split())
    claim = readme.index("imssr has run on torch ")
    # "imssr has run on torch 2.13.0 (CPU, the test suite) and 2.11.0+cu130 (the GPU figures ...)."
    ran = [Version(v).release for v in re.findall(r"\b(2\.\d+\.\d+)", readme[claim:readme.index(").", claim)])]
    assert len(ran) >= 2 and lower.release == min(ran)[:len(lower.release)], (str(lower), ran)
