"""``python -m controller_node``: see :mod:`controller_node.node`."""

from controller_node.node import main
from messages.cli import run_main

run_main(main)
