"""Measurement models. Each returns a :class:`agent.nav.kalman.Measurement` ``(z, H, R)``
with ``z`` = predicted minus measured and ``H`` the Jacobian w.r.t. the 15-state error."""
