"""``python -m gp_trainer``: see :mod:`gp_trainer.cli`."""

from gp_trainer.cli import main
from messages.cli import run_main

run_main(main)
