"""Where `python -m hdp_msgs_py.cli.main` went: the `hdp` command now lives in hdp_tools.

Published command lines (``torchrun --nproc-per-node 2 -m hdp_msgs_py.cli.main eval ...``) get
one line saying what to run instead, and exit 2, rather than a ModuleNotFoundError.
"""

import sys

MOVED = "hdp_msgs_py.cli.main moved: run 'hdp ...' or 'python -m hdp_tools.cli.main ...'"


def main(argv: list[str] | None = None) -> int:
    print(MOVED, file=sys.stderr)
    return 2


if __name__ == '__main__':
    sys.exit(main())
