"""``python -m bttsim_stream.nodes NAME [OPTIONS]``: run one node program by name."""

import sys

from bttsim_stream.nodes import MODULES, program
from bttsim_stream.runtime import run_node

if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] not in MODULES:
        print(f"usage: python -m bttsim_stream.nodes {{{','.join(MODULES)}}} [OPTIONS]", file=sys.stderr)
        sys.exit(2)
    sys.exit(run_node(program(sys.argv[1]), sys.argv[2:]))
