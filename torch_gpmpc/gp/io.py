"""The model file: one ``torch.save`` of tensors and strings, read back without running code.

A file is accepted only with a valid SHA-256 checksum over its entries: torch's zip
container does not verify its CRCs on load, so a damaged tensor (a flipped bit) would
otherwise load as a silently different model.
"""

from __future__ import annotations

import hashlib
import pickle
import warnings
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import atomic_path

FORMAT = "torch_gpmpc.ResidualGP"
VERSION = 1


def write_payload(path: str | Path, payload: dict) -> None:
    """Add the checksum and write ``payload`` to ``path`` atomically (``torch.save``)."""
    payload = {**payload, "checksum": payload_checksum(payload)}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def read_payload(path: Path, src: str) -> Any:
    """``torch.load(weights_only=True)`` of ``path`` (never runs code); every failure is a
    GpmpcError naming ``src``."""
    if not path.is_file():
        raise GpmpcError(f"{src}: file not found; fit one with `gpmpc fit-gp --out FILE`")
    if path.stat().st_size == 0:
        raise GpmpcError(f"{src}: cannot be read: the file is empty (an interrupted copy?); "
                         "fit one with `gpmpc fit-gp --out FILE`")
    if _is_numpy_archive(path):
        raise GpmpcError(f"{src}: is a NumPy archive (transitions or a rollout), not a GP model; fit one from "
                         f"transitions with `gpmpc fit-gp --transitions {path.name} --out gp.pt`")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. "Detected pickle protocol 4"
            return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if "GLOBAL" in str(exc):
            raise GpmpcError(f"{src}: refused to load: it references Python code or objects other "
                             "than tensors (an unsafe or foreign pickle); only files written by "
                             "ResidualGP.save are accepted") from None
        raise GpmpcError(f"{src}: cannot be read (corrupt or truncated file, or unsupported "
                         "pickle content); only files written by ResidualGP.save are accepted") from None
    except Exception as exc:  # torch raises RuntimeError/EOFError/ValueError... on garbage
        first = (str(exc).splitlines() or [""])[0].split(". ")[0]  # torch's miniz errors run on
        raise GpmpcError(f"{src}: cannot be read (corrupt, truncated or not a torch file: "
                         f"{type(exc).__name__}: {first}); fit one with `gpmpc fit-gp --out FILE`") from None


def _is_numpy_archive(path: Path) -> bool:
    """Whether ``path`` is a zip of ``.npy`` entries (``numpy.savez``), which torch's loader
    would report as a corrupt torch file."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except (zipfile.BadZipFile, OSError):
        return False
    return bool(names) and all(name.endswith(".npy") for name in names)


def payload_checksum(payload: dict) -> str:
    """SHA-256 over every entry except ``checksum`` (names, dtypes, shapes and bytes of tensors).

    torch's zip container does not verify its CRCs on load, so without this a damaged
    tensor (a flipped bit) would load as a silently different model.
    """
    digest = hashlib.sha256()

    def feed(key: str, value: Any) -> None:
        digest.update(key.encode())
        if isinstance(value, dict):
            for k in sorted(value):
                feed(f"{key}/{k}", value[k])
        elif isinstance(value, Tensor):
            t = value.detach().cpu().contiguous()
            digest.update(f"{t.dtype}{tuple(t.shape)}".encode())
            digest.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
        else:
            digest.update(repr(value).encode())

    for key in sorted(k for k in payload if k != "checksum"):
        feed(key, payload[key])
    return digest.hexdigest()




def verify_checksum(payload: dict, src: str) -> None:
    """Raise unless ``payload`` carries the checksum of its entries.

    Raises:
        GpmpcError: missing or mismatching checksum.
    """
    if "checksum" not in payload:
        raise GpmpcError(f"{src}: the file has no checksum, so its integrity cannot be verified; "
                         "refit it with `gpmpc fit-gp` (which writes one)")
    if payload["checksum"] != payload_checksum(payload):
        raise GpmpcError(f"{src}: checksum mismatch, the file is corrupt (damaged or modified after "
                         "it was written); copy it again or refit with `gpmpc fit-gp`")
