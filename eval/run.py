"""Research script: one closed-loop scenario -> metrics.json, rollout.npz, figures, TensorBoard.

Thin over the library: the same as `gpmpc run ...`. Run from the repository root,
e.g. `python eval/run.py --help`.
"""

import sys

from torch_gpmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["run", *sys.argv[1:]]))
