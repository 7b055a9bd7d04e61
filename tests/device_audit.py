"""A torch function mode that records the device of every tensor the audited code creates without an input tensor.

Shared by the device tests of the learners (``test_cig_td3_device.py``, ``test_ppo_device.py``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten


class CreationAudit(TorchFunctionMode):
    """Records every tensor the audited files create from no input tensor, with the device it lands on.

    Each such call (``torch.zeros(())``, ``torch.as_tensor(array, device=x.device)``, ...) is replayed
    once with the default device set to ``meta``: a call that names no device lands there, one that
    takes its device from an input tensor or the module lands on that device. The real call then
    runs unchanged: a replay on a real device draws from forked global generators or a copy of the
    call's ``generator``, so the audit changes no random numbers. A call given a ``generator`` is marked
    seeded: CoPO draws on a CPU generator on purpose (bit-identical seeded runs) and moves the draw.
    """

    def __init__(self, audited: tuple[Path, ...]) -> None:
        super().__init__()
        self.audited = audited  # the directories whose calls are audited
        self.created: list[tuple[str, str, torch.device, bool]] = []  # (file:line, function, device, seeded)

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        caller = sys._getframe(1)
        if Path(caller.f_code.co_filename).parent in self.audited:
            leaves, _ = tree_flatten((args, kwargs))
            if not any(isinstance(x, torch.Tensor) for x in leaves):
                replay = dict(kwargs)
                if isinstance(kwargs.get("generator"), torch.Generator):
                    replay["generator"] = torch.Generator(kwargs["generator"].device).set_state(kwargs["generator"].get_state())
                cuda = list(range(torch.cuda.device_count())) if torch.cuda.is_initialized() else []
                with torch.random.fork_rng(devices=cuda), torch.device("meta"):
                    probe = func(*args, **replay)
                if isinstance(probe, torch.Tensor):
                    where = f"{Path(caller.f_code.co_filename).name}:{caller.f_lineno}"
                    seeded = kwargs.get("generator") is not None
                    self.created.append((where, getattr(func, "__name__", repr(func)), probe.device, seeded))
        return func(*args, **kwargs)
