"""The GP melt-pool models as the controller and the surrogate plant run them (paper eq. 1-5, 8).

:class:`gp_model.model.GPModel` is the one-step model of the MPC and the feed-forward controller,
:class:`gp_model.narx.NarxGPModel` the delay-aware model of the preview MPC; both are read from and
written to versioned JSON files (:mod:`gp_model.files`), the shipped ones in ``gp_model/models/``.
They are trained by :mod:`gp_trainer`, which sits above the plant and the controller; this package
imports neither.
"""
