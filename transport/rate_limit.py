"""Token buckets on a caller's clock: how the radio shares the channel among transmitters and how
an agent bounds the signature verifications a sender can cost (both in sensor time, so that a
run's outcome does not depend on the machine's speed)."""

from __future__ import annotations

from collections.abc import Hashable


class TokenBuckets:
    """One bucket per key: ``rate`` tokens a second [1/s], at most ``burst`` held; each
    :meth:`take` spends one. A new key starts full. Keep the keys to a known, bounded set (the
    fleet's vehicles): the buckets are never forgotten."""

    def __init__(self, rate: float, burst: float) -> None:
        if not (rate > 0 and burst >= 1):
            raise ValueError(f"a token bucket needs rate > 0 and burst >= 1, got {rate} and {burst}")
        self.rate, self.burst = float(rate), float(burst)
        self._buckets: dict[Hashable, tuple[float, float]] = {}  #: key -> (tokens, at time [s])

    def take(self, key: Hashable, now: float) -> bool:
        """Spend a token of ``key`` at time ``now`` [s]; False (nothing spent) if it has none."""
        tokens, at = self._buckets.get(key, (self.burst, now))
        tokens = min(self.burst, tokens + max(0.0, now - at) * self.rate)
        ok = tokens >= 1.0
        self._buckets[key] = (tokens - 1.0 if ok else tokens, max(at, now))
        return ok
