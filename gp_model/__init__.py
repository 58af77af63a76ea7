"""The GP melt-pool models as the controller and the surrogate plant run them (paper eq. 1-5, 8).

:class:`gp_model.model.GPModel` is the one-step model of the MPC and the feed-forward controller,
:class:`gp_model.narx.NarxGPModel` the delay-aware model of the preview MPC; both are read from and
written to versioned JSON files (:mod:`gp_model.files`), the shipped ones in ``gp_model/models/``.
They are trained by :mod:`gp_trainer`, which sits above the plant and the controller; this package
imports neither.

>>> import numpy as np
>>> from gp_model.model import GPModel
>>> from gp_model.shipped import ONE_STEP_MODEL_PATH
>>> model = GPModel.load(ONE_STEP_MODEL_PATH)
>>> z = np.array([0.06e-6, 600.0, 200.0, 0.8, 0.0])  # area [m²], T ahead [K], power [W], speed [m/s], area change [m²]
>>> mean_m2, variance_m4 = model.predict(z)           # the next state's area
>>> 0 < mean_m2 < 1e-6 and variance_m4 > 0
True
"""
