"""Training pipeline of the GP melt-pool models (paper eq. 1-5, 8), above the plant and the controller.

It turns recorded plant states into training samples (:mod:`gp_trainer.dataset`), picks training
points (:mod:`gp_trainer.selection`), fits and evaluates the models of :mod:`gp_model`
(:mod:`gp_trainer.train`, :mod:`gp_trainer.narx_fit`) and runs the data campaigns on the FE plant
(:mod:`gp_trainer.campaign`). Command line: ``python -m gp_trainer --help``.
"""
