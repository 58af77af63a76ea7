"""GP dynamics model of the melt pool and its training pipeline (paper eq. 1-5, 8).

:class:`gp_trainer.model.GPModel` is the model the MPC consumes; the rest of the package turns
recorded plant states into training samples (:mod:`gp_trainer.dataset`), picks training points
(:mod:`gp_trainer.selection`), fits and evaluates the model and orchestrates the Table 2 data
campaign (:mod:`gp_trainer.campaign`). Command line: ``python -m gp_trainer --help``.
"""
