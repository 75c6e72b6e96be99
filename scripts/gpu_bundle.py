"""Build the folder a bare GPU machine installs imssr's missing packages from, with no index.

    python scripts/gpu_bundle.py [--python 3.12] [--out .gpu-bundle] [--no-debs] [--limit-mib 64]

A leased GPU machine (the prepared commands ``scripts/gpu_results.sh`` and
``scripts/gpu_seeds.sh``) has Python, torch and most of imssr's requirements, but not
dm_control, MuJoCo, gymnasium, omegaconf, docstring-parser and their own small needs, nor
Debian's EGL and OpenGL loader libraries, and it cannot download anything.  Everything it gets
travels with the repository, 64 MiB in all, and dm_control's wheel alone is 56 MB.  This script
makes, in ``--out`` (default ``.gpu-bundle/`` in the checkout, which git ignores: name it among
what the GPU machine is sent, a device call's ``carry``):

- the wheels of :data:`CARRIED` for ``--python`` on x86-64 Linux, at the versions of
  ``constraints.txt``, downloaded with pip from the index pip is configured with;
- dm_control's and MuJoCo's wheels rewritten without what imssr never loads (:data:`TRIM`):
  dm_control keeps its control suite (every domain, the dog's assets too) and what the suite
  imports, MuJoCo keeps its bindings, its classic renderer and its plugins; each wheel stays
  valid (its RECORD lists the files kept, with their hashes) and says in
  ``*.dist-info/IMSSR_TRIMMED.txt`` what was left out;
- the ``.deb`` files of :data:`DEBS` (``apt-get download``, amd64), each unpacked on the GPU
  machine only where its library is missing there and no EGL or OpenGL loader is found
  (``--no-debs``: none);
- ``imssr-source.json``, the checkout's source stamp (``python -m imssr.provenance --stamp``):
  the commit each run's ``provenance.json`` names on a machine without ``.git``;
- ``bundle.json``: the Python version, each file and its size.

It prints the folder's size and the total with what else travels (git's tracked files and
untracked files it does not ignore), and exits with status 2 when that total is over
``--limit-mib``.  ``scripts/gpu_common.sh`` installs the folder, when it is there, before
anything imports imssr.  Every requirement of a carried wheel and of imssr must be carried, be
one the GPU image holds (:data:`IMAGE`), or be left out with its reason (:data:`LEFT_OUT`):
the script checks this, so that a new version's new requirement is not missed.
``tests/test_gpu_bundle.py`` builds the folder for the test's own Python, installs it with
``--no-index`` beside only torch and the image's packages, imports imssr and renders a frame
of every task the prepared commands train.
"""
from __future__ import annotations

import argparse
import base64
import csv
import fnmatch
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CARRIED = ("dm_control", "mujoco", "dm-env", "dm-tree", "glfw", "PyOpenGL", "gymnasium", "Farama-Notifications",
           "omegaconf", "docstring_parser")
"""The distributions the GPU image lacks that imssr imports: dm_control and what its suite needs
(MuJoCo, dm-env, dm-tree, glfw, PyOpenGL), gymnasium (with Farama-Notifications), omegaconf and
docstring-parser."""

IMAGE = ("torch", "numpy", "scipy", "tqdm", "matplotlib", "tensorboard", "pillow", "scikit-image", "scikit-learn",
         "imageio", "absl-py", "lxml", "protobuf", "pyparsing", "requests", "setuptools", "attrs", "wrapt",
         "cloudpickle", "typing-extensions", "PyYAML", "etils")
"""The requirements of imssr and of the carried wheels that the GPU image holds (as its package
list reads on the leased H200s: Python 3.12 with torch 2.11)."""

LEFT_OUT = {
    "labmaze": "dm_control.locomotion's mazes, which the trimmed dm_control does not carry",
    "websockets": "MuJoCo's experimental studio, which the trimmed MuJoCo does not carry",
    "imageio-ffmpeg": "mp4 evaluation videos only (train.eval_video_format=mp4); the default gif needs none",
}
"""Requirements not carried, each with what alone needs it."""

TRIM = {
    "dm_control": {
        "keep": ["dm_control/__init__.py", "dm_control/_render/*", "dm_control/mjcf/*", "dm_control/mujoco/*",
                 "dm_control/rl/*", "dm_control/suite/*", "dm_control/utils/*", "dm_control-*.dist-info/*"],
        "drop": ["dm_control/mujoco/testing/*", "dm_control/mjcf/test_assets/*", "dm_control/suite/demos/*",
                 # The suite's interactive explorer imports dm_control.viewer, which is not carried.
                 "dm_control/suite/explore.py", "*_test.py"],
        "why": "imssr loads dm_control.suite and dm_control.mujoco.engine; kept: the suite (every domain) "
               "and the packages it imports (_render, mjcf, mujoco, rl, utils); left out: locomotion, "
               "manipulation, composer, entities, viewer, blender, autowrap, third_party, the test assets "
               "and tests",
    },
    "mujoco": {
        "keep": ["*"],
        "drop": ["mujoco/experimental/*", "mujoco/_render_filament*", "mujoco/mjrf.py", "mujoco/rendering/filament/*",
                 "mujoco/_simulate*", "mujoco/viewer.py", "mujoco/sysid/*", "mujoco/usd/*", "mujoco/testdata/*",
                 "*_test.py"],
        "why": "imssr renders through dm_control with MuJoCo's classic OpenGL renderer; left out: the "
               "experimental studio and its GUI libraries, the Filament renderer, the interactive "
               "viewer, sysid, the USD exporter, the test data and tests",
    },
}
"""Per trimmed wheel: the files kept (glob patterns on the paths inside the wheel), those dropped
from them, and why (written into the wheel's ``IMSSR_TRIMMED.txt``)."""

DEBS = {"libegl1": "EGL", "libglvnd0": "GLdispatch", "libopengl0": "OpenGL", "libgl1": "GL", "libglx0": "GLX"}
"""Debian's EGL and OpenGL loaders (glvnd), each with the library it provides: NVIDIA's driver
brings the vendor library they load."""

PLATFORMS = [f"manylinux_2_{n}_x86_64" for n in range(28, 4, -1)] + [
    "manylinux2014_x86_64", "manylinux2010_x86_64", "manylinux1_x86_64"]
"""pip matches ``--platform`` tags exactly: every manylinux tag up to glibc 2.28, which the
machines in use (glibc 2.36 and later) run."""

STAMP = "imssr-source.json"
"""The source stamp's name in the folder; ``--install`` puts it beside the package as
``.imssr-source.json`` (:data:`imssr.provenance.SOURCE_STAMP`)."""

UNREACHABLE = (r"NewConnectionError|Failed to establish a new connection|Temporary failure in name resolution|"
               r"Name or service not known|Network is unreachable|No route to host|ConnectTimeout|ProxyError")
"""What pip's warnings say when the package index cannot be reached."""

LIMIT_MIB = 64
"""What travels to the device machine, the repository's files and the carried folders, in MiB."""


class BundleError(Exception):
    """A failure told in one line."""


def normalize(name: str) -> str:
    """A distribution's name as PEP 503 compares it."""
    return re.sub(r"[-_.]+", "-", name).lower()


def pinned(constraints: str, names) -> dict[str, str]:
    """``name -> version`` of ``names`` from the ``name==version`` lines of ``constraints``."""
    try:
        with open(constraints, encoding="utf-8") as fh:
            lines = fh.read().splitlines()
    except OSError as exc:
        raise BundleError(f"cannot read {constraints}: {exc.strerror}") from None
    pins = {}
    for line in lines:
        m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)\s*==\s*([^\s;#]+)", line)
        if m:
            pins[normalize(m.group(1))] = m.group(2)
    missing = [n for n in names if normalize(n) not in pins]
    if missing:
        raise BundleError(f"{constraints} pins no version of {', '.join(missing)}")
    return {n: pins[normalize(n)] for n in names}


def requirement_names(metadata: str) -> set[str]:
    """The names a wheel's METADATA requires outside its extras."""
    names = set()
    for line in metadata.splitlines():
        if line.startswith("Requires-Dist:") and "extra ==" not in line:
            m = re.match(r"Requires-Dist:\s*([A-Za-z0-9][A-Za-z0-9._-]*)", line)
            if m:
                names.add(normalize(m.group(1)))
    return names


def imssr_requirements() -> set[str]:
    """The names of imssr's own requirements (pyproject.toml's ``dependencies``)."""
    import tomllib

    with open(os.path.join(REPO, "pyproject.toml"), "rb") as fh:
        deps = tomllib.load(fh)["project"]["dependencies"]
    return {normalize(re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", d).group(0)) for d in deps}


def check_requirements(wheels: list[str]) -> None:
    """Every requirement of imssr and of the carried ``wheels`` is carried, held by the image or
    left out with a reason; a name that is none of these is a one-line error."""
    known = {normalize(n) for n in (*CARRIED, *IMAGE, *LEFT_OUT)}
    unknown = {}
    for name in imssr_requirements() - known:
        unknown[name] = "imssr"
    for path in wheels:
        with zipfile.ZipFile(path) as z:
            meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
            for name in requirement_names(z.read(meta).decode("utf-8", "replace")) - known:
                unknown.setdefault(name, os.path.basename(path).split("-")[0])
    if unknown:
        raise BundleError("requirements neither carried, held by the GPU image nor left out: "
                          + ", ".join(f"{n} (of {who})" for n, who in sorted(unknown.items()))
                          + "; add each to CARRIED, IMAGE or LEFT_OUT in scripts/gpu_bundle.py")


def pip_download(versions: dict[str, str], python: str, dest: str) -> list[str]:
    """Download the wheels of ``versions`` for CPython ``python`` on x86-64 Linux into ``dest``;
    returns their paths.  pip's own cache serves a repeated download."""
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version", python,
           "--implementation", "cp", "--disable-pip-version-check", "-q", "-d", dest]
    for tag in PLATFORMS:
        cmd += ["--platform", tag]
    cmd += [f"{n}=={v}" for n, v in versions.items()]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        lines = proc.stderr.splitlines()
        # Without a network pip retries, warns, and then finds "no versions": the warning says why.
        unreachable = [m for m in map(re.compile(UNREACHABLE).search, lines) if m]
        if unreachable:
            where = unreachable[-1].string.rsplit("': ", 1)[-1].strip() if "': " in unreachable[-1].string else "?"
            raise BundleError(f"pip download cannot reach the package index ({unreachable[-1].group(0)} on {where})")
        errors = [line for line in lines if line.startswith("ERROR")] or lines
        raise BundleError(f"pip download failed: {(errors or ['no output'])[0]}")
    wheels = sorted(os.path.join(dest, f) for f in os.listdir(dest) if f.endswith(".whl"))
    if len(wheels) != len(versions):
        raise BundleError(f"pip download gave {len(wheels)} wheels for {len(versions)} distributions")
    return wheels


def _record_hash(data: bytes) -> str:
    return "sha256=" + base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()


def _matches(name: str, patterns) -> bool:
    return any(fnmatch.fnmatchcase(name, p) for p in patterns)


def trim_wheel(src: str, dest: str, rules: dict) -> tuple[int, int]:
    """Write the wheel ``src`` to ``dest`` with only the files ``rules`` keeps, a new RECORD and an
    ``IMSSR_TRIMMED.txt`` in its dist-info; returns the files kept and dropped."""
    with zipfile.ZipFile(src) as zin:
        infos = [i for i in zin.infolist() if not i.is_dir()]
        record = next(i.filename for i in infos if re.fullmatch(r"[^/]+\.dist-info/RECORD", i.filename))
        dist_info = record.rsplit("/", 1)[0]
        kept = [i for i in infos if i.filename != record and _matches(i.filename, rules["keep"])
                and not _matches(i.filename, rules["drop"])]
        dropped = len(infos) - 1 - len(kept)
        rows = []
        with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as zout:
            for info in kept:
                data = zin.read(info)
                out = zipfile.ZipInfo(info.filename, date_time=info.date_time)
                out.external_attr, out.compress_type = info.external_attr, zipfile.ZIP_DEFLATED
                zout.writestr(out, data)
                rows.append((info.filename, _record_hash(data), str(len(data))))
            note = (f"Rewritten by imssr's scripts/gpu_bundle.py from {os.path.basename(src)}: "
                    f"{len(kept)} files kept, {dropped} left out.\n{rules['why']}.\n"
                    f"Kept: {' '.join(rules['keep'])}\nLeft out of those: {' '.join(rules['drop'])}\n").encode()
            zout.writestr(f"{dist_info}/IMSSR_TRIMMED.txt", note)
            rows.append((f"{dist_info}/IMSSR_TRIMMED.txt", _record_hash(note), str(len(note))))
            rows.append((record, "", ""))
            text = io.StringIO()
            csv.writer(text, lineterminator="\n").writerows(rows)
            zout.writestr(record, text.getvalue())
    return len(kept), dropped


def apt_download(packages, dest: str) -> list[str]:
    """Download the amd64 ``.deb`` files of ``packages`` into ``dest``; returns their paths."""
    if shutil.which("apt-get") is None:
        raise BundleError("apt-get is not here to download Debian's EGL libraries: run on Debian or Ubuntu, "
                          "or pass --no-debs")
    arch = subprocess.run(["dpkg", "--print-architecture"], capture_output=True, text=True).stdout.strip()
    if arch != "amd64":
        # apt-get downloads for the architecture its package lists describe: the one it runs on.
        raise BundleError(f"apt-get here downloads {arch or 'another architecture'}'s packages and the GPU machine is "
                          "x86-64: make the folder on an x86-64 machine, or pass --no-debs")
    opts = ["-q"]
    if os.geteuid() == 0:
        opts += ["-o", "APT::Sandbox::User=root"]  # apt's own user cannot write a root-owned folder
    proc = subprocess.run(["apt-get", *opts, "download", *packages], cwd=dest, capture_output=True, text=True)
    if proc.returncode != 0:
        errors = [line for line in proc.stderr.splitlines() if line.startswith("E:")] or ["no output"]
        raise BundleError(f"apt-get download failed: {errors[0]} (run apt-get update first; or pass --no-debs)")
    return sorted(os.path.join(dest, f) for f in os.listdir(dest) if f.endswith(".deb"))


def write_stamp(dest: str) -> str:
    """The checkout's source stamp (what ``python -m imssr.provenance --stamp`` writes) in
    ``dest``; returns its commit, or why there is none."""
    sys.path.insert(0, REPO)
    try:
        from imssr.errors import ImssrError
        from imssr.provenance import write_stamp as stamp_checkout
    except ImportError as exc:
        return f"none (imssr does not import with {sys.executable}: {exc})"
    try:
        path = stamp_checkout(REPO, os.path.join(dest, STAMP))
    except ImssrError as exc:
        return f"none ({exc})"
    with open(path, encoding="utf-8") as fh:
        stamp = json.load(fh)
    return stamp["commit"][:12] + ("" if stamp.get("clean") else " (tracked files modified)")


def travelling_bytes(out: str) -> int:
    """Bytes of the checkout that travel without being named: git's tracked files and the
    untracked ones it does not ignore (``out`` left out, when it is among them)."""
    proc = subprocess.run(["git", "-C", REPO, "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise BundleError(f"{REPO} is not a git checkout: cannot tell what travels with the folder")
    out = os.path.abspath(out) + os.sep
    total = 0
    for name in set(proc.stdout.split("\0")) - {""}:
        path = os.path.join(REPO, name)
        if not (os.path.abspath(path) + os.sep).startswith(out) and os.path.isfile(path):
            total += os.path.getsize(path)
    return total


def folder_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(path) for f in files)


def mib(n: int) -> str:
    return f"{n / 2 ** 20:.1f} MiB"


def build(out: str, python: str, constraints: str, debs: bool = True) -> dict:
    """Make the folder ``out`` (replacing what it held); returns its manifest (``bundle.json``)."""
    if not re.fullmatch(r"3\.\d+", python):
        raise BundleError(f"--python {python!r} must be a CPython version such as 3.12")
    versions = pinned(constraints, CARRIED)
    parent = os.path.dirname(os.path.abspath(out))
    os.makedirs(parent, exist_ok=True)
    stage = tempfile.mkdtemp(prefix=".gpu-bundle-", dir=parent)
    try:
        downloads = os.path.join(stage, "downloads")
        os.makedirs(downloads)
        folder = os.path.join(stage, "bundle")
        os.makedirs(folder)
        wheels = pip_download(versions, python, downloads)
        check_requirements(wheels)
        manifest = {"python": python, "wheels": [], "debs": [], "stamp": None}
        for path in wheels:
            name = os.path.basename(path)
            dest = os.path.join(folder, name)
            rules = next((r for dist, r in TRIM.items() if normalize(name.split("-")[0]) == normalize(dist)), None)
            entry = {"file": name, "downloaded_bytes": os.path.getsize(path)}
            if rules is None:
                shutil.copyfile(path, dest)
            else:
                entry["files_kept"], entry["files_left_out"] = trim_wheel(path, dest, rules)
            entry["bytes"] = os.path.getsize(dest)
            manifest["wheels"].append(entry)
        if debs:
            manifest["debs"] = [{"file": os.path.basename(p), "bytes": os.path.getsize(p)}
                                for p in apt_download(DEBS, folder)]
        manifest["stamp"] = write_stamp(folder)
        with open(os.path.join(folder, "bundle.json"), "w", encoding="utf-8") as fh:
            json.dump(manifest, fh, indent=1)
            fh.write("\n")
        if os.path.isdir(out):
            shutil.rmtree(out)
        os.replace(folder, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return manifest


def read_manifest(folder: str) -> dict:
    """The folder's ``bundle.json``; a folder without a readable one is a one-line error."""
    try:
        with open(os.path.join(folder, "bundle.json"), encoding="utf-8") as fh:
            manifest = json.load(fh)
    except (OSError, ValueError):
        manifest = None
    if not (isinstance(manifest, dict) and isinstance(manifest.get("python"), str)
            and all(isinstance(manifest.get(k), list) and all(isinstance(e, dict) and isinstance(e.get("file"), str)
                                                              for e in manifest[k]) for k in ("wheels", "debs"))):
        raise BundleError(f"{folder} has no readable bundle.json: make it with python scripts/gpu_bundle.py")
    return manifest


def installed_version(name: str):
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def install(folder: str) -> list[str]:
    """Install the folder into this Python's environment (what ``scripts/gpu_common.sh`` runs on
    the GPU machine before anything imports imssr); returns what it did, a line each:

    - the wheels, with pip and no index, unless each is installed at its version already (then
      nothing, so that a machine with its own packages keeps them); a folder made for another
      Python is a one-line error only where something is to install;
    - where no EGL or OpenGL loader is found (``ldconfig``'s cache), the ``.deb`` files of the
      libraries missing, unpacked into ``/`` (as root): a machine's own libraries are never
      overwritten;
    - the source stamp, copied beside the package where the checkout has neither ``.git`` nor a
      stamp of its own."""
    import ctypes.util

    manifest = read_manifest(folder)
    notes = []
    wheels = [os.path.join(folder, w["file"]) for w in manifest["wheels"]]
    absent = [os.path.basename(w) for w in wheels if not os.path.isfile(w)]
    if absent:
        raise BundleError(f"{folder} lacks {', '.join(absent)}: make it again with python scripts/gpu_bundle.py")
    # A wheel's file name begins with its distribution's name and version.
    to_install = [w for w in wheels if installed_version(os.path.basename(w).split("-")[0])
                  != os.path.basename(w).split("-")[1]]
    if not to_install:
        notes.append(f"packages: the {len(wheels)} of {folder} are installed here already")
    else:
        here = "%d.%d" % sys.version_info[:2]
        if manifest["python"] != here:
            raise BundleError(f"{folder} holds wheels for Python {manifest['python']} and this is Python {here}: "
                              f"make it with python scripts/gpu_bundle.py --python {here}")
        proc = subprocess.run([sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "-q",
                               "--disable-pip-version-check", *to_install], capture_output=True, text=True)
        if proc.returncode != 0:
            errors = [line for line in proc.stderr.splitlines() if line.startswith("ERROR")] or proc.stderr.splitlines()
            raise BundleError(f"pip install from {folder} failed: {(errors or ['no output'])[0]}")
        names = [os.path.basename(w).split("-")[0] for w in to_install]
        notes.append(f"packages: installed from {folder} with no index: {' '.join(names)}")
    # A .deb file's name begins with its package's name.
    missing = [d["file"] for d in manifest["debs"]
               if not ctypes.util.find_library(DEBS.get(d["file"].split("_")[0], d["file"]))]
    if all(ctypes.util.find_library(lib) for lib in ("EGL", "OpenGL")):
        notes.append("EGL and OpenGL loaders: the machine's own")
    elif missing:
        if os.geteuid() != 0:
            raise BundleError(f"no EGL or OpenGL loader here, and unpacking {folder}'s .deb files into / needs root")
        for deb in missing:
            proc = subprocess.run(["dpkg", "-x", os.path.join(folder, deb), "/"], capture_output=True, text=True)
            if proc.returncode != 0:
                raise BundleError(f"dpkg -x {deb} failed: {(proc.stderr.strip().splitlines() or ['?'])[0]}")
        subprocess.run(["ldconfig"], check=False)
        notes.append(f"EGL and OpenGL loaders: unpacked from {folder}: {' '.join(missing)}")
    else:
        notes.append(f"EGL and OpenGL loaders: none here and none in {folder}")
    if os.path.exists(os.path.join(REPO, ".git")):
        notes.append("source: the git checkout")
    elif os.path.exists(os.path.join(REPO, "." + STAMP)):
        notes.append(f"source stamp: the checkout's own .{STAMP}")
    elif os.path.isfile(os.path.join(folder, STAMP)):
        shutil.copyfile(os.path.join(folder, STAMP), os.path.join(REPO, "." + STAMP))
        notes.append(f"source stamp: {manifest.get('stamp')}, from {folder}")
    else:
        notes.append("source stamp: none (runs record the commit as unknown)")
    return notes


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--python", default="3.12", help="the GPU machine's Python version (default 3.12)")
    p.add_argument("--out", default=os.path.join(REPO, ".gpu-bundle"),
                   help="the folder to make (default .gpu-bundle in the checkout; replaced when it exists)")
    p.add_argument("--constraints", default=os.path.join(REPO, "constraints.txt"),
                   help="the versions to carry (name==version lines; default constraints.txt)")
    p.add_argument("--no-debs", action="store_true", help="carry no Debian EGL libraries")
    p.add_argument("--limit-mib", type=float, default=LIMIT_MIB,
                   help=f"the most the folder and the checkout's files may take together (default {LIMIT_MIB})")
    p.add_argument("--install", metavar="FOLDER",
                   help="install FOLDER into this Python's environment instead (what scripts/gpu_common.sh runs)")
    args = p.parse_args(argv)
    try:
        if args.install:
            for line in install(args.install):
                print(line)
            return 0
        manifest = build(args.out, args.python, args.constraints, debs=not args.no_debs)
        size = folder_bytes(args.out)
        repo = travelling_bytes(args.out)
        for w in manifest["wheels"]:
            trimmed = f", {w['files_left_out']} files left out" if "files_left_out" in w else ""
            print(f"{w['file']}: {mib(w['bytes'])} (downloaded {mib(w['downloaded_bytes'])}{trimmed})")
        for d in manifest["debs"]:
            print(f"{d['file']}: {d['bytes'] / 1024:.0f} KiB")
        print(f"source stamp: {manifest['stamp']}")
        print(f"{os.path.relpath(args.out)}: {mib(size)}; with the checkout's {mib(repo)}: {mib(size + repo)} "
              f"of {args.limit_mib:g} MiB")
        if size + repo > args.limit_mib * 2 ** 20:
            raise BundleError(f"{mib(size + repo)} is over the {args.limit_mib:g} MiB that travel")
        return 0
    except BundleError as exc:
        print(f"gpu_bundle: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
