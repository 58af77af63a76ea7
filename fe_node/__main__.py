"""``python -m fe_node [node|run|validate] ...``; no subcommand or ``node`` starts the zenoh node."""
import sys

from messages.cli import run_main


def _main(argv: list[str]) -> int:
    if not argv or argv[0] == "node" or argv[0].startswith("-") and argv[0] not in ("-h", "--help"):
        from fe_node.node import main  # the zenoh wrapper, imported lazily
        return main(argv[1:] if argv and argv[0] == "node" else argv)
    from fe_node.cli import main
    return main(argv)


run_main(_main, sys.argv[1:])
