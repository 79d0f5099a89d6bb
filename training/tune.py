"""Research script: gradient tuning of rho and the risk split through the unrolled ADMM.

Thin over the library: the same as `gpmpc tune ...`. Run from the repository root,
e.g. `python training/tune.py --help`.
"""

import sys

from torch_gpmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["tune", *sys.argv[1:]]))
