"""``slcp.X`` as the top-level module ``X``, for a copy of the tree without the links under
``slcp/``: mutmut copies the package into ``mutants/`` without them and keeps the mutants of
``agent/nav/fusion.py`` as ``agent.nav.fusion``. With this finder the tests run the mutated code,
one module object under both names (``slcp/__init__.py`` installs it only in such a copy)."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """``slcp.X`` as the top-level module ``X`` of the copy, one module object under both names."""

    def find_spec(self, fullname, path=None, target=None):  # type: ignore[no-untyped-def]
        if not fullname.startswith("slcp."):
            return None
        found = importlib.util.find_spec(fullname.partition(".")[2])
        if found is None:
            return None
        return importlib.util.spec_from_loader(fullname, self, is_package=found.submodule_search_locations is not None)

    def create_module(self, spec):  # type: ignore[no-untyped-def]
        module = importlib.import_module(spec.name.partition(".")[2])
        spec.loader_state = module.__spec__  # the import sets the alias's spec on the module
        return module

    def exec_module(self, module):  # type: ignore[no-untyped-def]
        module.__spec__ = module.__spec__.loader_state

    def get_code(self, fullname):  # type: ignore[no-untyped-def]  # python -m slcp.X runs X's code
        target = fullname.partition(".")[2]
        return importlib.util.find_spec(target).loader.get_code(target)


def install() -> None:
    sys.meta_path.insert(0, _Alias())
