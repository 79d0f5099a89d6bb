"""Research script: fit one residual GP per state dimension from logged transitions.

Thin over the library: the same as `gpmpc fit-gp ...`. Run from the repository root,
e.g. `python training/fit_gp.py --help`.
"""

import sys

from torch_gpmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["fit-gp", *sys.argv[1:]]))
