"""Wire layer: frozen messages, the msgpack codec, key expressions and the Bus (Zenoh or
in-memory). Only :mod:`transport.zenoh_bus` imports zenoh."""
