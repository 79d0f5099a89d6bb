"""Research script: the paper's six methods, figures 1-6 and a results table.

Thin over the library: the same as `gpmpc reproduce ...`. Run from the repository root,
e.g. `python eval/reproduce.py --help`.
"""

import sys

from torch_gpmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["reproduce", *sys.argv[1:]]))
