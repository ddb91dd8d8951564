"""The house rules a newcomer relies on, checked statically over the three packages.

- data flow one way (doedesign -> masks -> metrology) by every import, lazy ones included;
- no library module of masks or metrology reaches into a command-line module of another package
  (their own command modules may use only the shared helpers, ``doedesign.cli.common``);
- CONTRIBUTING.md's "where each stage lives" table names files that exist and every (sub)package.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("doedesign", "masks", "metrology")
RANK = {name: i for i, name in enumerate(PACKAGES)}
SHARED_COMMAND_HELPERS = "doedesign.cli.common"


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            yield name, path


def _imports(name, path):
    """Absolute names of every module ``path`` imports, wherever the import statement sits."""
    is_package = path.name == "__init__.py"
    here = name.split(".") if is_package else name.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = here[:len(here) - node.level + 1] if node.level else []
            mod = ".".join(base + ([node.module] if node.module else []))
            out.add(mod)
            # "from pkg import sub" imports a module too; the callers below only look at prefixes.
            out |= {f"{mod}.{a.name}" for a in node.names}
    return out


def _is_cli(module):
    return "cli" in module.split(".")


def test_imports_flow_one_way():
    upward = []
    for name, path in _modules():
        own = RANK[name.split(".")[0]]
        for target in _imports(name, path):
            top = target.split(".")[0]
            if top in RANK and RANK[top] > own:
                upward.append(f"{name} imports {target}")
    assert not upward, upward


def test_no_library_module_imports_another_packages_command_line():
    bad = []
    for name, path in _modules():
        if name.split(".")[0] == "doedesign":
            continue
        for target in _imports(name, path):
            if target.split(".")[0] == name.split(".")[0] or not _is_cli(target):
                continue
            allowed = _is_cli(name) and (target == SHARED_COMMAND_HELPERS
                                         or target.startswith(SHARED_COMMAND_HELPERS + "."))
            if not allowed:
                bad.append(f"{name} imports {target}")
    assert not bad, bad


def test_the_import_scan_sees_lazy_and_relative_imports(tmp_path):
    # The scan above must catch what it guards against: an import inside a function, and a
    # relative import resolved against the package.
    pkg = tmp_path / "metrology" / "sub"
    pkg.mkdir(parents=True)
    src = pkg / "mod.py"
    src.write_text("def f():\n    from doedesign.cli.design import X\n\nfrom ..formats import readers\n")
    found = _imports("metrology.sub.mod", src)
    assert "doedesign.cli.design" in found and "metrology.formats.readers" in found


def _stage_table():
    text = (ROOT / "CONTRIBUTING.md").read_text()
    section = text.split("## Where each stage lives", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("|")][2:]
    assert rows, "CONTRIBUTING.md: the 'where each stage lives' table is empty"
    return rows


def _named_paths(row):
    """Paths a table row names: `pkg/dir/` sets the folder, `pkg/x.py` is whole, `x.py` is in the folder."""
    folder, paths = None, []
    for token in re.findall(r"`([^`]+)`", row.split("|")[2]):
        if token.endswith("/"):
            folder = token.rstrip("/")
            paths.append(folder)
        elif token.endswith(".py"):
            if "/" in token:
                folder = str(Path(token).parent)
                paths.append(token)
            else:
                assert folder, f"CONTRIBUTING.md row {row!r}: {token} named before any folder"
                paths.append(f"{folder}/{token}")
    return paths


def test_readme_stage_table_matches_the_tree():
    named = [p for row in _stage_table() for p in _named_paths(row)]
    missing = [p for p in named if not (ROOT / p).exists()]
    assert not missing, f"CONTRIBUTING.md names files that do not exist: {missing}"
    named_dirs = {p if (ROOT / p).is_dir() else str(Path(p).parent) for p in named}
    packages = {str(init.parent.relative_to(ROOT)) for pkg in PACKAGES for init in (ROOT / pkg).rglob("__init__.py")}
    unnamed = sorted(packages - named_dirs)
    assert not unnamed, f"CONTRIBUTING.md's stage table does not name these packages: {unnamed}"
    modules = {str(p.relative_to(ROOT)) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")
               if p.name != "__init__.py"}
    unnamed_modules = sorted(m for m in modules if not _folder_named_whole(m, named))
    assert not unnamed_modules, f"CONTRIBUTING.md's stage table does not name these modules: {unnamed_modules}"


def _folder_named_whole(module, named):
    # A module counts as named if the table names it, or names its folder (`pkg/sub/`) as a whole.
    return module in named or str(Path(module).parent) in named


@pytest.mark.parametrize("row", ["| x | `metrology/formats/`: `readers.py`, `nope.py` |"])
def test_the_table_parser_resolves_short_names_against_the_folder(row):
    assert _named_paths(row) == ["metrology/formats", "metrology/formats/readers.py", "metrology/formats/nope.py"]
