"""slcp: stop-line-aided cooperative positioning for connected vehicles.

Installed, the repository's top-level folders are this package's subpackages (``slcp/`` links
to each): ``slcp.agent`` (the vehicle's engine and navigation core), ``slcp.vehicles`` (vehicle
profiles), ``slcp.geo`` (the site
layer), ``slcp.transport`` (messages, codec, security, the bus), ``slcp.hw_emulation`` (the
emulated world) and ``slcp.deploy`` (operations, the lab and the command line).
"""

import os as _os

if not _os.path.isdir(_os.path.join(_os.path.dirname(__file__), "agent")):  # mutmut's copy
    from ._mutation_copy import install as _install

    _install()
