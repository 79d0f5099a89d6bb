"""Moving the protocol's messages: point-to-point float64 tensors with deadlines, and the
process group (gloo, 127.0.0.1 by default)."""

from __future__ import annotations

import datetime
import logging
import os
import socket
import time

import torch
from torch import Tensor

from torch_gpmpc.coordination.distributed.protocol import DTYPE
from torch_gpmpc.errors import GpmpcError

log = logging.getLogger(__name__)


class Network:
    """Point-to-point float64 messages with deadlines over ``torch.distributed``.

    Every receive has a deadline; a peer that does not answer, or whose connection
    closes, is marked dead for good (:attr:`dead`, rank -> reason).
    """

    def __init__(self, rank: int) -> None:
        import torch.distributed as dist

        self.dist = dist
        self.rank = rank
        self.dead: dict[int, str] = {}  # rank -> reason

    def _lost(self, peer: int, exc: BaseException | str) -> None:
        if peer not in self.dead:
            reason = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            self.dead[peer] = reason
            log.warning("rank %d: lost contact with rank %d (%s)", self.rank, peer, reason)

    def exchange(self, sends: list[tuple[Tensor, int, int]], recvs: list[tuple[tuple[int, ...], int, int]],
                 timeout_s: float, dtype: torch.dtype = DTYPE) -> list[Tensor | None]:
        """Post all sends and receives, then wait for them before one deadline.

        Args:
            sends: ``(tensor, dst rank, tag)``.
            recvs: ``(shape, src rank, tag)``.
            timeout_s: seconds until the deadline.

        Returns:
            One tensor per receive, ``None`` where the peer was (or became) unreachable.
        """
        deadline = time.monotonic() + timeout_s
        send_works = []
        for tensor, dst, tag in sends:
            if dst in self.dead:
                continue
            try:
                send_works.append((self.dist.isend(tensor.contiguous(), dst, tag=tag), dst, tensor))
            except RuntimeError as exc:
                self._lost(dst, exc)
        posted = []
        for shape, src, tag in recvs:
            if src in self.dead:
                posted.append(None)
                continue
            buf = torch.empty(shape, dtype=dtype)
            try:
                posted.append((self.dist.irecv(buf, src, tag=tag), src, buf))
            except RuntimeError as exc:
                self._lost(src, exc)
                posted.append(None)
        out: list[Tensor | None] = []
        for item in posted:
            if item is None:
                out.append(None)
                continue
            work, src, buf = item
            if src in self.dead or not self._wait(work, src, deadline):
                out.append(None)
            else:
                out.append(buf)
        for work, dst, _ in send_works:
            if dst not in self.dead:
                self._wait(work, dst, deadline)
        return out

    def _wait(self, work, peer: int, deadline: float) -> bool:
        remaining = max(deadline - time.monotonic(), 0.01)
        try:
            ok = work.wait(datetime.timedelta(seconds=remaining))
        except RuntimeError as exc:
            self._lost(peer, exc)
            return False
        if ok is False:
            self._lost(peer, "no answer within the deadline")
            return False
        return True

    def send_bytes(self, payload: bytes, dst: int, tag: int, timeout_s: float) -> None:
        data = torch.frombuffer(bytearray(payload), dtype=torch.uint8)
        self.exchange([(torch.tensor([float(data.numel())], dtype=DTYPE), dst, tag)], [], timeout_s)
        self.exchange([(data, dst, tag + 1)], [], timeout_s)

    def recv_bytes(self, src: int, tag: int, timeout_s: float) -> bytes | None:
        (n,) = self.exchange([], [((1,), src, tag)], timeout_s)
        if n is None:
            return None
        (data,) = self.exchange([], [((int(n.item()),), src, tag + 1)], timeout_s, dtype=torch.uint8)
        return None if data is None else bytes(data.numpy().tobytes())


def env_rank() -> int | None:
    """``RANK`` from the environment when launched by torchrun or by hand, else ``None``."""
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        return int(os.environ["RANK"])
    return None


def is_agent_rank() -> bool:
    """Whether this process was launched (torchrun / env variables) as an agent rank (> 0)."""
    rank = env_rank()
    return rank is not None and rank > 0


def free_port() -> int:
    """A free TCP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def init_group(rank: int, world_size: int, timeout_s: float, init_method: str = "env://") -> None:
    """Join the gloo process group as ``rank``.

    Raises:
        GpmpcError: a process group already exists in this process.
    """
    import torch.distributed as dist

    if dist.is_initialized():
        raise GpmpcError("distributed run: a torch.distributed process group is already initialised "
                         "in this process")
    dist.init_process_group("gloo", init_method=init_method, rank=rank, world_size=world_size,
                            timeout=datetime.timedelta(seconds=timeout_s))


def destroy_group() -> None:
    """Leave the process group, if any (errors while tearing down after a fault are only logged)."""
    import torch.distributed as dist

    if dist.is_initialized():
        try:
            dist.destroy_process_group()
        except Exception as exc:  # noqa: BLE001 - tearing down after a fault
            log.debug("destroy_process_group: %s", exc)
