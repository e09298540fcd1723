"""The mutation tool's copy of the tree: mutmut copies ``slcp/`` without its links to the
top-level folders and keeps the mutants of ``agent/nav/fusion.py`` as ``agent.nav.fusion``.
There, ``slcp.X`` must be the copy's module ``X`` (one object under both names), or the tests
would run the installed, unmutated code and every mutant would "survive" with no test."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_in_a_copy_without_the_links_slcp_x_is_the_copys_module_x(tmp_path) -> None:
    (tmp_path / "slcp").mkdir()
    for name in ("__init__.py", "_mutation_copy.py"):
        shutil.copy(ROOT / "slcp" / name, tmp_path / "slcp" / name)
    for pkg in ("agent", "agent/nav"):
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "agent" / "nav" / "fusion.py").write_text("from . import helper\nWHO = 'the copy'\n")
    (tmp_path / "agent" / "nav" / "helper.py").write_text("")
    (tmp_path / "agent" / "main.py").write_text("from .nav import fusion\nprint(__name__, fusion.WHO)\n")
    code = ("import sys; sys.path.insert(0, sys.argv[1])\n"
            "import slcp.agent.nav.fusion as a, agent.nav.fusion as b\n"
            "assert a is b and a.WHO == 'the copy' and a.__name__ == 'agent.nav.fusion', a\n"
            "assert a.__spec__.name == 'agent.nav.fusion' and not hasattr(a, '__path__')\n"
            "import slcp.agent.nav as n; assert n is sys.modules['agent.nav'] and hasattr(n, '__path__')\n"
            "print('ok')\n")
    out = subprocess.run([sys.executable, "-W", "error", "-c", code, str(tmp_path)], capture_output=True,
                         text=True, timeout=60, cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
    # the tests start processes with ``python -m slcp....``
    out = subprocess.run([sys.executable, "-W", "error", "-m", "slcp.agent.main"], capture_output=True, text=True,
                         timeout=60, cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "__main__ the copy", out.stderr


def test_the_installed_package_is_not_aliased() -> None:
    import slcp.agent.nav.fusion as f

    assert f.__name__ == "slcp.agent.nav.fusion" and "agent.nav.fusion" not in sys.modules
