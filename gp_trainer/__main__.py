"""``python -m gp_trainer``: see :mod:`gp_trainer.cli`."""

import sys

from gp_trainer.cli import main

sys.exit(main())
