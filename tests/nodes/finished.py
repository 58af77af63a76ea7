"""A test node that ends with status 0 at once, before any liveliness token of it could be seen:
the limit of a short run that finishes faster than the launch service's readiness query.

``python -m tests.nodes.finished``
"""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    print("[finished] done before being seen", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
