"""Research script: log transitions of the true system (the paper's data recipe).

Thin over the library: the same as `gpmpc collect ...`. Run from the repository root,
e.g. `python training/collect.py --help`.
"""

import sys

from torch_gpmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["collect", *sys.argv[1:]]))
