"""slcp: stop-line-aided cooperative positioning for connected vehicles.

Installed, the repository's top-level folders are this package's subpackages (``slcp/`` links
to each): ``slcp.agent`` (the vehicle's engine and navigation core), ``slcp.vehicles`` (vehicle
profiles), ``slcp.geo`` (the site
layer), ``slcp.transport`` (messages, codec, security, the bus), ``slcp.hw_emulation`` (the
emulated world) and ``slcp.deploy`` (operations, the lab and the command line).
"""

import importlib as _importlib
import importlib.abc as _abc
import importlib.util as _util
import os as _os
import sys as _sys


class _Alias(_abc.MetaPathFinder, _abc.Loader):
    """``slcp.X`` as the top-level module ``X`` of the copy, one module object under both names."""

    def find_spec(self, fullname, path=None, target=None):  # type: ignore[no-untyped-def]
        if not fullname.startswith(__name__ + "."):
            return None
        module = _importlib.import_module(fullname.partition(".")[2])
        return _util.spec_from_loader(fullname, self, is_package=hasattr(module, "__path__"))

    def create_module(self, spec):  # type: ignore[no-untyped-def]
        module = _sys.modules[spec.name.partition(".")[2]]
        spec.loader_state = module.__spec__  # the import sets the alias's spec on the module
        return module

    def exec_module(self, module):  # type: ignore[no-untyped-def]
        module.__spec__ = module.__spec__.loader_state


# A copy of the tree without the links (mutmut copies ``slcp/`` into ``mutants/`` without them,
# and names the mutated modules ``agent.…``, ``geo.…``): ``slcp.X`` is the copy's module ``X``,
# so that the tests run the mutated code under the names the mutants are kept by.
if not _os.path.isdir(_os.path.join(_os.path.dirname(__file__), "agent")):
    _sys.meta_path.insert(0, _Alias())
