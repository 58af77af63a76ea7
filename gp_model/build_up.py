"""The pool's build-up after laser-on or a layer start, which the models are not fitted on.

Kept apart from :mod:`gp_model.narx` so that a controller's settings can name it without loading
the model's numerics (scipy, numba).
"""

BUILD_UP_STEPS = 20
"""Samples whose target lies in the first 20 steps after laser-on or a layer start (the pool builds
up) are neither fitted nor judged; the preview MPC's observer starts after them."""
