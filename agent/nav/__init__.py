"""Pure navigation core: numpy/scipy only (no asyncio, zenoh or msgpack).

Conventions: SI units and radians; local-level frame NED; body frame FRD;
error state ordered as in :mod:`agent.nav.state`; errors are estimate minus truth.
"""
