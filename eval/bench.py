"""Research script: performance workloads with ratios against baselines measured in the same run.

Thin over the library: the same as `gpmpc bench ...`. Run from the repository root,
e.g. `python eval/bench.py --help`.
"""

import sys

from torch_gpmpc.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
