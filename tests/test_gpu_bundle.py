"""scripts/gpu_bundle.py: the folder of packages a bare GPU machine installs with no index.

Built from PyPI for this test's own Python, it is installed by ``scripts/gpu_common.sh`` (what the
prepared GPU commands source) into a virtual environment that sees torch and the GPU image's
other packages alone, in a copy of the checkout without ``.git``; there imssr imports, every task
the prepared commands train renders a frame, every domain of the suite loads, and the device
record names the checkout's commit from the folder's source stamp."""
from __future__ import annotations

import base64
import csv
import hashlib
import io
import json
import os
import shutil
import subprocess
import sys
import zipfile
from importlib import metadata

import pytest
from packaging.requirements import Requirement

from conftest import REPO, load_script

bundle = load_script("scripts/gpu_bundle.py")
lease = load_script("scripts/lease_results.py")

CHECK = '''
import sys
import imssr, imssr.cli, imssr.training  # the CLI's and the trainer's modules (omegaconf, docstring-parser)
from imssr.envs import make_env
from dm_control import suite
import dm_control, mujoco

for task in sys.argv[1:]:
    obs, _ = make_env(task, seed=1).reset(seed=1)
    print("frame", task, obs.shape, float(obs.std()))
domains = sorted({d for d, _ in suite.ALL_TASKS})
for domain in domains:
    suite.load(domain, next(t for d, t in suite.ALL_TASKS if d == domain)).reset()
print("domains", len(domains))
print("from", dm_control.__file__, mujoco.__file__)
'''
"""Run in the GPU-like environment: imports, one frame per task given, every suite domain."""


def trained_tasks() -> list[str]:
    """The tasks scripts/gpu_results.sh trains (the sweep files of its plan) and the one
    scripts/gpu_seeds.sh trains (bench/seeds.py's, bench/step_time.py's: cartpole_swingup)."""
    base, steps = lease.read_plan(os.path.join(REPO, "docs", "results", "lease_plan.json"))
    return sorted({task for step in steps for task in lease.sweep_of(base, step).tasks} | {"cartpole_swingup"})


def image_closure() -> dict[str, metadata.Distribution]:
    """This environment's distributions of :data:`bundle.IMAGE` and pip, and what they require
    (extras left out): what the GPU image holds of imssr's needs."""
    seen, todo = {}, [*bundle.IMAGE, "pip"]
    while todo:
        name = bundle.normalize(todo.pop())
        if name in seen:
            continue
        dist = seen[name] = metadata.distribution(name)
        for text in dist.requires or []:
            req = Requirement(text)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                todo.append(req.name)
    return seen


def image_venv(path) -> str:
    """A virtual environment at ``path`` that sees :func:`image_closure` alone, each linked from
    this environment; returns its Python."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(path)], check=True)
    python = os.path.join(path, "bin", "python")
    site = subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    carried = {bundle.normalize(n) for n in bundle.CARRIED}
    for name, dist in image_closure().items():
        assert name not in carried, name
        assert dist.files is not None, name
        for top in {f.parts[0] for f in dist.files if f.parts[0] != ".."}:
            if not os.path.lexists(os.path.join(site, top)):
                os.symlink(dist.locate_file(top), os.path.join(site, top))
    return python


def copy_checkout(dest) -> None:
    """The checkout's files that git tracks or does not ignore, as they are in the work tree,
    without ``.git`` (what a device call sends)."""
    names = subprocess.run(["git", "-C", REPO, "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                           capture_output=True, text=True, check=True).stdout.split("\0")
    for name in filter(None, names):
        src = os.path.join(REPO, name)
        if os.path.isfile(src):
            os.makedirs(os.path.join(dest, os.path.dirname(name)), exist_ok=True)
            shutil.copy2(src, os.path.join(dest, name))


def assert_valid_record(path) -> None:
    """The wheel's RECORD lists each of its files once, with its sha256 and size."""
    with zipfile.ZipFile(path) as z:
        record = next(n for n in z.namelist() if n.endswith(".dist-info/RECORD"))
        rows = {row[0]: row[1:] for row in csv.reader(io.StringIO(z.read(record).decode()))}
        assert set(rows) == {i.filename for i in z.infolist() if not i.is_dir()}
        for name, (digest, size) in rows.items():
            if name != record:
                data = z.read(name)
                encoded = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
                assert digest == "sha256=" + encoded
                assert size == str(len(data))


def clean_env(**extra) -> dict:
    """This process's environment without what would let a Python see other packages."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    return {**env, "PYTHONNOUSERSITE": "1", **extra}


def test_a_bare_machine_imports_imssr_and_renders_every_trained_task_from_the_folder(tmp_path):
    copy = tmp_path / "copy"
    copy_checkout(copy)
    folder = copy / ".gpu-bundle"
    python = "%d.%d" % sys.version_info[:2]
    built = subprocess.run([sys.executable, os.path.join(REPO, "scripts", "gpu_bundle.py"), "--python", python,
                            "--out", str(folder), "--no-debs"], capture_output=True, text=True, timeout=600)
    if built.returncode != 0 and "cannot reach the package index" in built.stderr:
        pytest.skip(f"needs PyPI, unreachable here: {built.stderr.strip()}")
    assert built.returncode == 0, built.stdout + built.stderr
    assert "MiB of 64 MiB" in built.stdout
    manifest = json.loads((folder / "bundle.json").read_text())
    assert manifest["python"] == python and manifest["debs"] == []
    assert sorted(bundle.normalize(w["file"].split("-")[0]) for w in manifest["wheels"]) == \
        sorted(bundle.normalize(n) for n in bundle.CARRIED)
    for w in manifest["wheels"]:
        if "files_left_out" in w:
            assert_valid_record(folder / w["file"])
    venv_python = image_venv(tmp_path / "venv")
    seen = subprocess.run([venv_python, "-c", "import importlib.util as u; print([n for n in ('dm_control', "
                           "'mujoco', 'gymnasium', 'omegaconf', 'docstring_parser') if u.find_spec(n)])"],
                          capture_output=True, text=True, env=clean_env(), check=True).stdout
    assert seen.strip() == "[]"  # the venv lacks what the folder carries
    (tmp_path / "check.py").write_text(CHECK)
    out = tmp_path / "out"
    tasks = trained_tasks()
    proc = subprocess.run(["bash", "-c", 'SCRIPT=gpu_test OUT_DIR="$1" BUDGET_S=60 source scripts/gpu_common.sh '
                           '&& "$PY" "$2" "${@:3}"', "bash", str(out), str(tmp_path / "check.py"), *tasks],
                          cwd=copy, capture_output=True, text=True, timeout=600,
                          env=clean_env(PYTHON=venv_python, MUJOCO_GL="egl"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "packages: installed from .gpu-bundle with no index: dm_control" in proc.stdout
    for task in tasks:
        line = next(x for x in proc.stdout.splitlines() if x.startswith(f"frame {task} "))
        assert "(9, 100, 100)" in line and float(line.split()[-1]) > 1, line  # a picture, not a blank
    from imssr.envs.tasks import SUITE_TASKS

    assert f"domains {len({d for d, _ in SUITE_TASKS})}" in proc.stdout
    venv_site = os.path.realpath(tmp_path / "venv")
    loaded_from = next(x for x in proc.stdout.splitlines() if x.startswith("from ")).split()[1:]
    assert all(os.path.realpath(p).startswith(venv_site + os.sep) for p in loaded_from), loaded_from
    head = subprocess.run(["git", "-C", REPO, "rev-parse", "HEAD"], capture_output=True, text=True,
                          check=True).stdout.strip()
    device = (out / "device.txt").read_text()
    assert f"source stamp: {manifest['stamp']}, from .gpu-bundle" in device
    assert f"\ngit_commit: {head}\n" in device, device


def test_an_unusable_folder_stops_the_gpu_scripts_in_one_line(tmp_path):
    folder = tmp_path / "bundle"
    folder.mkdir()
    env = clean_env(GPU_BUNDLE=str(folder), PYTHON=sys.executable)
    command = ["bash", "-c", 'SCRIPT=gpu_test OUT_DIR="$1" BUDGET_S=60 source scripts/gpu_common.sh && echo sourced',
               "bash", str(tmp_path / "out")]
    proc = subprocess.run(command, cwd=REPO, capture_output=True, text=True, env=env)
    assert proc.returncode == 2 and "sourced" not in proc.stdout
    assert proc.stderr == f"gpu_bundle: error: {folder} has no readable bundle.json: make it with python " \
                          "scripts/gpu_bundle.py\n"
    assert (tmp_path / "out" / "device.txt").read_text() == proc.stderr
    # A folder for another Python, with a wheel this environment lacks.
    (folder / "bundle.json").write_text(json.dumps(
        {"python": "3.99", "wheels": [{"file": "imssr_absent-1.0-py3-none-any.whl"}], "debs": []}))
    (folder / "imssr_absent-1.0-py3-none-any.whl").write_bytes(b"")
    proc = subprocess.run(command, cwd=REPO, capture_output=True, text=True, env=env)
    here = "%d.%d" % sys.version_info[:2]
    assert proc.returncode == 2 and proc.stderr == (
        f"gpu_bundle: error: {folder} holds wheels for Python 3.99 and this is Python {here}: "
        f"make it with python scripts/gpu_bundle.py --python {here}\n")
