"""docs/architecture.md's module map is the package's tree: every module it names exists, and
every module of the package is named there (a package's own ``__init__.py`` aside)."""
import os
import re

from conftest import REPO


def _map_entries() -> set[str]:
    """The module paths (relative to imssr/) that the map's code block names: a line's first
    column of names, nested under the folder lines above it by indentation (two spaces a level);
    description lines, indented further, are skipped."""
    with open(os.path.join(REPO, "docs", "architecture.md")) as fh:
        text = fh.read()
    block = text[text.index("```\nimssr/\n") + len("```\nimssr/\n"):]
    block = block[:block.index("```")]
    entries, folders = set(), []
    for line in block.splitlines():
        indent = len(line) - len(line.lstrip(" "))
        if not line.strip() or indent >= 19:
            continue
        names = re.match(r"([\w./]+(?:, [\w./]+)*)", line.strip()).group(1).split(", ")
        folders = folders[:indent // 2 - 1]
        for name in names:
            if not name.endswith("/"):
                entries.add("/".join([*folders, name]))
        if names[-1].endswith("/"):
            folders.append(names[-1].rstrip("/"))
    return entries


def test_the_module_map_names_every_module_and_nothing_else():
    package = os.path.join(REPO, "imssr")
    modules = {os.path.relpath(os.path.join(d, f), package) for d, dirs, files in os.walk(package)
               for f in files if f.endswith(".py")}
    modules = {m for m in modules if os.path.basename(m) != "__init__.py" or m == "__init__.py"}
    entries = _map_entries()
    assert sorted(entries - modules) == [], "named in docs/architecture.md but not in imssr/"
    assert sorted(modules - entries) == [], "in imssr/ but not in docs/architecture.md's module map"


def test_the_settings_layer_reads_no_run_directory():
    """Presets and configs build settings; a resumed run's saved config is read by the training's
    entry point (imssr/training/entry.py), so neither imports the run directory's code."""
    for folder in ("config", "presets"):
        for name in os.listdir(os.path.join(REPO, "imssr", folder)):
            if name.endswith(".py"):
                with open(os.path.join(REPO, "imssr", folder, name)) as fh:
                    assert not re.search(r"^\s*(from|import) imssr\.(rundir|training)\b", fh.read(), re.M), \
                        f"imssr/{folder}/{name} imports the run directory or training code"
