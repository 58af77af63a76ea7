"""``python -m controller_node``: see :mod:`controller_node.node`."""

import sys

from controller_node.node import main

sys.exit(main())
