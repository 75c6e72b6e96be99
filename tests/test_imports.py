"""The package's import structure: no import circle, and every module imports on its own."""
import ast
import os
import subprocess
import sys
import textwrap

import pytest

from conftest import curve, make_run
import imssr

PACKAGE_DIR = os.path.dirname(imssr.__file__)


def _modules() -> dict[str, str]:
    """Every module of the package: dotted name -> file."""
    found = {}
    for folder, _, files in os.walk(PACKAGE_DIR):
        for name in files:
            if not name.endswith(".py"):
                continue
            rel = os.path.relpath(os.path.join(folder, name), os.path.dirname(PACKAGE_DIR))
            dotted = rel[:-3].replace(os.sep, ".").removesuffix(".__init__")
            found[dotted] = os.path.join(folder, name)
    return found


def _type_checking_only(tree: ast.AST) -> set[int]:
    """ids of the import nodes under ``if TYPE_CHECKING:`` (never run)."""
    skipped = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skipped.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return skipped


def import_graph(type_checking: bool = False) -> dict[str, set[str]]:
    """Module -> the package's modules it imports, at the top or inside functions (and under
    ``if TYPE_CHECKING:`` with ``type_checking``)."""
    modules = _modules()
    graph = {}
    for name, path in modules.items():
        with open(path, encoding="utf-8") as fh:
            tree = ast.parse(fh.read(), path)
        skipped = set() if type_checking else _type_checking_only(tree)
        package = name if path.endswith("__init__.py") else name.rpartition(".")[0]
        edges = set()
        for node in ast.walk(tree):
            if id(node) in skipped:
                continue
            if isinstance(node, ast.Import):
                edges.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
                for alias in node.names:
                    # `from pkg import mod` imports the module pkg.mod; `from mod import name` imports mod.
                    edges.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
        graph[name] = {e for e in edges if e in modules and e != name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str]:
    """One import circle as a path ``[a, b, ..., a]``, or [] when the graph is acyclic."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str]:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        path.pop()
        state[node] = 2
        return []

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return []


def test_the_import_graph_has_no_circle():
    graph = import_graph()
    assert {"imssr.config", "imssr.presets", "imssr.cli", "imssr.sweep.grid"} <= set(graph)
    assert "imssr.presets" in graph["imssr.sweep.grid"]  # in-function imports count too
    cycle = find_cycle(graph)
    assert not cycle, " -> ".join(cycle)


def test_layers_do_not_reach_up(tmp_path):
    """Imported as they run (package ``__init__`` files included): the run directory knows
    nothing of training; the sweep starts trainings as processes and loads no trainer; the
    report reads files and loads neither the trainer nor the sweep's dispatch."""
    code = textwrap.dedent("""
        import importlib, sys
        def loaded_by(name):
            before = set(sys.modules)
            importlib.import_module(name)
            return {m for m in set(sys.modules) - before if m.startswith("imssr.")}
        print(sorted(loaded_by("imssr.rundir") & {"imssr.training", "imssr.training.loop", "imssr.agents"}))
        print(sorted(loaded_by("imssr.sweep.sweep") & {"imssr.training", "imssr.training.loop"}))
        report = loaded_by("imssr.report.report") | loaded_by("imssr.report.export")
        print(sorted(report & {"imssr.training", "imssr.training.loop", "imssr.sweep.sweep", "imssr.sweep.runner"}))
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split("\n")[:3] == ["[]", "[]", "[]"], proc.stdout


def test_the_settings_and_the_plugins_declarations_import_nothing_above_them():
    """settings/ imports nothing of imssr but itself and errors; a plug-in's *_spec.py nothing but
    settings/; the registries nothing but those and their own package; config/ none of the
    plug-ins' torch code nor anything that uses a config; ``TYPE_CHECKING`` blocks included."""
    graph = import_graph(type_checking=True)
    settings = {m for m in graph if m.startswith("imssr.settings")}
    specs = {m for m in graph if m.endswith("_spec")}
    assert {"imssr.auxiliary.curl_spec", "imssr.intrinsic.ssl_spec"} <= specs
    for name in settings | specs:
        assert graph[name] <= settings | {"imssr.errors"}, (name, graph[name] - settings)
    for package in ("imssr.auxiliary", "imssr.intrinsic"):
        for name in (package, f"{package}.registry"):
            outside = {m for m in graph[name] if not m.startswith(package + ".")}
            assert outside <= settings | {"imssr.errors"}, (name, outside)
    above = ("imssr.agents", "imssr.training", "imssr.rundir", "imssr.presets", "imssr.sweep", "imssr.report",
             "imssr.analysis", "imssr.plots", "imssr.networks", "imssr.cli", "imssr.api", "imssr.console")
    torch_code = {m for m in graph if m.startswith(("imssr.auxiliary.", "imssr.intrinsic."))
                  and not m.endswith(("_spec", ".registry"))}
    for name in (m for m in graph if m.startswith("imssr.config")):
        assert not {m for m in graph[name] if m.startswith(above) or m in torch_code}, (name, graph[name])


def test_the_settings_load_no_torch():
    """The config, the presets and the registries read the plug-ins' declarations, not their code."""
    code = ("import sys, imssr.config, imssr.presets, imssr.auxiliary, imssr.intrinsic; "
            "imssr.presets.make_config('im-soda', 'walker_walk').validate(); "
            "assert 'soda' in imssr.auxiliary.AUX_TASKS and 'rnd' in imssr.intrinsic.INTRINSIC_SIGNALS; "
            "print('torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) == []


# Each module is imported in a process of its own, forked from one that has imported the
# heavy third-party libraries but no imssr module: each child starts without any of the
# package in sys.modules, as `python -c "import imssr.X"` would, in a fraction of the time.
_IMPORT_EACH = textwrap.dedent("""
    import importlib, os, sys, traceback
    import numpy, torch  # noqa: F401  (third-party only: the children share them)
    for heavy in ("omegaconf", "gymnasium", "PIL.Image", "tqdm", "rliable.library", "rliable.metrics"):
        try:
            importlib.import_module(heavy)
        except ImportError:  # an extra that is not installed: the child finds out
            pass
    assert not any(m == "imssr" or m.startswith("imssr.") for m in sys.modules)
    failed = []
    for name in sys.argv[1:]:
        pid = os.fork()
        if pid == 0:
            try:
                importlib.import_module(name)
            except BaseException:
                traceback.print_exc()
                os._exit(1)
            os._exit(0)
        _, status = os.waitpid(pid, 0)
        if status != 0:
            failed.append(name)
    print("FAILED:", " ".join(failed))
    sys.exit(1 if failed else 0)
""")


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_every_module_imports_on_its_own():
    names = sorted(m for m in _modules() if not m.endswith("__main__"))  # __main__ runs the CLI
    proc = subprocess.run([sys.executable, "-c", _IMPORT_EACH, *names], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-4000:]
    assert proc.stdout.strip() == "FAILED:"


def _seeds(root, n: int) -> str:
    """A sweep root with ``n`` seeds of one algo on one task."""
    for seed in range(1, n + 1):
        make_run(str(root), "curl", seed, curve(0, 100, 100 * seed))
    return str(root)


def test_a_missing_extra_is_one_line_naming_it(tmp_path):
    """Without Ray, `imssr sweep` fails in one line naming the sweep extra."""
    code = textwrap.dedent(f"""
        import sys
        sys.modules["ray"] = None  # as if Ray were not installed
        from imssr.cli import main
        code = main(["sweep", "--algos", "curl", "--tasks", "walker_walk", "--steps", "10",
                     "--root", {str(tmp_path / "sweep")!r}, "--no-progress"])
        assert code == 2, code
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("imssr: error: ray is not installed") and "pip install 'imssr[sweep]'" in lines[0]
    assert not (tmp_path / "sweep").exists()  # nothing written before the error


def _report_without_rliable(root: str) -> subprocess.CompletedProcess:
    """``imssr report ROOT`` in a process where rliable cannot be imported (as if the report
    extra were not installed); it must exit 0."""
    code = textwrap.dedent(f"""
        import sys
        sys.modules["rliable"] = None
        from imssr.cli import main
        assert main(["report", {root!r}, "--reps", "20"]) == 0
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_a_report_with_an_iqm_due_is_made_without_the_report_extra_but_for_the_iqm(tmp_path):
    """Five seeds, where an IQM is due, and no rliable: the tables, comparisons and curves are
    written all the same (they need no rliable), and one warning and the report's notes say that
    the IQM needs the report extra."""
    proc = _report_without_rliable(_seeds(tmp_path / "five", 5))
    why = "no IQM: rliable is not installed (needed by imssr report): pip install 'imssr[report]'"
    warnings = [line for line in proc.stdout.splitlines() if "warning" in line]
    assert len(warnings) == 1 and warnings[0].startswith(f"imssr: warning: {why}"), proc.stdout
    assert proc.stderr == ""
    out = tmp_path / "five" / "report"
    for name in ("evaluations.csv", "table.csv", "comparisons.csv", "curves.png"):
        assert os.path.getsize(out / name) > 0, name
    assert open(out / "aggregates.csv").read().count("\n") == 1  # the header alone
    assert "| `cartpole_swingup_sparse` | curl |" in (out / "report.md").read_text()
    assert f"- {why}" in (out / "report.md").read_text()


def test_a_report_without_an_iqm_needs_no_report_extra(tmp_path):
    """Fewer than 5 seeds give no IQM or bootstrap interval: the report is made without rliable."""
    _report_without_rliable(_seeds(tmp_path / "four", 4))
    assert "no IQM or bootstrap interval: curl has 4 seeds" in (tmp_path / "four" / "report" / "report.md").read_text()


def test_the_cli_answers_what_needs_no_training_without_torch():
    # Each in a fresh process: --help, the listings, the preset, every subcommand's --help.
    commands = [["--help"], ["tasks"], ["algos"], ["modes"], ["config", "--algo", "im-curl", "--task", "walker_walk"],
                *[[name, "--help"] for name in ("train", "demo", "evaluate", "analyze", "plot", "sweep", "report",
                                                "export", "config", "modes", "tasks", "algos")]]
    probe = textwrap.dedent("""
        import contextlib, io, sys
        from imssr.console import main
        with contextlib.redirect_stdout(io.StringIO()) as out:
            try:
                code = main(sys.argv[1:])
            except SystemExit as exc:
                code = exc.code
        heavy = sorted(m for m in ("torch", "dm_control", "mujoco", "matplotlib") if m in sys.modules)
        print(code, len(out.getvalue()) > 0, heavy)
    """)
    for argv in commands:
        proc = subprocess.run([sys.executable, "-c", probe, *argv], capture_output=True, text=True, timeout=120)
        assert proc.stdout.split("\n")[0] in ("0 True []", "None True []"), (argv, proc.stdout, proc.stderr[-2000:])
