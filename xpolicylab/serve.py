"""``python -m xpolicylab.serve key=value ...``: the same as ``xpolicylab serve``."""

import sys

from xpolicylab.cli import serve_main

if __name__ == "__main__":
    sys.exit(serve_main(sys.argv[1:]))
