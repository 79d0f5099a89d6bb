"""``python -m torch_gpmpc.cli.distributed [gpmpc run options]``: one entry for every rank.

Under torchrun (``RANK`` set) rank 0 is ``gpmpc run --backend distributed [options]`` and
every other rank hosts agents (ignoring the options).
"""

from __future__ import annotations

import logging
import os
import sys

from torch_gpmpc.coordination.distributed.agent_process import agent_main
from torch_gpmpc.coordination.distributed.transport import is_agent_rank


def main(argv: list[str] | None = None) -> int:
    """Serve agents on an agent rank, else run the world (``gpmpc run --backend distributed``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if is_agent_rank():
        logging.basicConfig(level=logging.INFO if "-v" in argv or "--verbose" in argv else logging.WARNING,
                            format=f"%(levelname)s rank{os.environ['RANK']} %(name)s: %(message)s")
        return agent_main()
    from torch_gpmpc.cli import main as cli_main

    return cli_main(["run", "--backend", "distributed", *argv])


if __name__ == "__main__":  # pragma: no cover - process entry
    sys.exit(main())
