"""The habits the tools check: the import contracts of the layers (import-linter), ruff, mypy
(strict on the navigation core, the site layer and the transport), and modules and functions of
a readable size. Each runs on the source tree the suite tests, with the project's own
configuration (pyproject.toml)."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("agent", "transport", "hw_emulation", "deploy", "geo", "vehicles")
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80


def _tool(name: str) -> str:
    """The tool next to this interpreter (the venv the project was installed into)."""
    path = Path(sys.executable).parent / name
    found = str(path) if path.exists() else shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: it comes with the dev extra (pip install '.[dev]')")
    return found


def _run(*cmd: str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600)


def test_the_layers_keep_their_import_contracts() -> None:
    """The emulator never imports the agent; the agent imports neither the operations, the lab
    nor the emulator; the navigation core and the engine do no I/O; one module imports Zenoh."""
    out = _run(_tool("lint-imports"))
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "0 broken" in out.stdout and "The emulator never imports the agent KEPT" in out.stdout


def test_ruff_passes() -> None:
    out = _run(_tool("ruff"), "check", "--no-cache", ".")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]


@pytest.mark.slow
def test_mypy_passes_on_the_typed_core() -> None:
    out = _run(_tool("mypy"), "--no-incremental")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]


def _sizes() -> tuple[list[str], list[str]]:
    modules, functions = [], []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            src = path.read_text()
            rel = path.relative_to(REPO)
            if len(src.splitlines()) > MAX_MODULE_LINES:
                modules.append(f"{rel}: {len(src.splitlines())} lines")
            for node in ast.walk(ast.parse(src)):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                n = node.end_lineno - node.lineno + 1
                doc = ast.get_docstring(node) or ""
                if n > MAX_FUNCTION_LINES and "Long:" not in doc:
                    functions.append(f"{rel}:{node.lineno} {node.name}: {n} lines")
    return modules, functions


def test_modules_and_functions_are_small() -> None:
    """No module over 500 lines; no function over 80 unless its docstring says why, on a line
    starting ``Long:``."""
    modules, functions = _sizes()
    assert not modules, modules
    assert not functions, functions
