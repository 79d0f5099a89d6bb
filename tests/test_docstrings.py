"""Every public class has a runnable example in its docstring, and every example runs."""

from __future__ import annotations

import doctest
import importlib
import inspect

import pytest

import torch_gpmpc

PUBLIC_CLASSES = sorted(name for name in torch_gpmpc.__all__ if inspect.isclass(getattr(torch_gpmpc, name)))


def test_every_public_class_has_an_example():
    missing = [name for name in PUBLIC_CLASSES if ">>>" not in (getattr(torch_gpmpc, name).__doc__ or "")]
    assert not missing, f"public classes without a runnable example: {missing}"


def _modules() -> list[str]:
    names = {getattr(torch_gpmpc, name).__module__ for name in torch_gpmpc.__all__}
    return sorted(names | {"torch_gpmpc.control.solvers", "torch_gpmpc.gp.protocol"})


@pytest.mark.parametrize("module", _modules())
def test_docstring_examples_run(module):
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.NORMALIZE_WHITESPACE,
                             verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {module}"
