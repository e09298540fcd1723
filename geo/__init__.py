"""The site layer: the earth model and the lane-marking classes.

Both the vehicle's estimator (:mod:`agent`) and the emulated world (:mod:`hw_emulation`) stand
on this layer; it imports neither (numpy only).
"""
