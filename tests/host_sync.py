"""A CPU detector of host-device synchronisations (the CPU twin of torch's CUDA sync debug mode).

On a CUDA device, ``.item()``, ``bool(t)`` (a Python ``if`` on a tensor), ``float(t)``, ``tolist``,
``nonzero``, boolean-mask indexing and blocking copies to the host wait for the GPU, and inside
``torch.cuda.graph`` capture they fail. On the CPU they cost nothing and go unseen; under
:func:`no_host_sync` every such call raises :class:`HostSync`, naming the op, so a CPU test can prove
that a code path would not synchronise (or break a capture) on a GPU.
"""

from __future__ import annotations

import torch
from torch.overrides import TorchFunctionMode

_T = torch.Tensor
# ops that read a device value on the host (or need it to size their output)
SYNC_OPS = {
    _T.item: "Tensor.item", _T.tolist: "Tensor.tolist", _T.__bool__: "bool(Tensor)",
    _T.__float__: "float(Tensor)", _T.__int__: "int(Tensor)", _T.__index__: "Tensor.__index__",
    _T.numpy: "Tensor.numpy", _T.cpu: "Tensor.cpu", _T.nonzero: "Tensor.nonzero", torch.nonzero: "torch.nonzero",
    torch.argwhere: "torch.argwhere", torch.masked_select: "torch.masked_select", _T.masked_select: "masked_select",
    torch.unique: "torch.unique", _T.unique: "Tensor.unique",
}


class HostSync(RuntimeError):
    """An op that synchronises with the host ran inside :func:`no_host_sync`."""


def _has_bool_index(index) -> bool:
    items = index if isinstance(index, tuple) else (index,)
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in items)


# patched on the class as well: autograd runs a custom Function's backward outside the torch-function
# mode, so the mode alone would miss a sync inside a law's backward
_PATCHED = {"item": "Tensor.item", "tolist": "Tensor.tolist", "__bool__": "bool(Tensor)",
            "__float__": "float(Tensor)", "__int__": "int(Tensor)", "nonzero": "Tensor.nonzero",
            "numpy": "Tensor.numpy", "cpu": "Tensor.cpu"}


def _raiser(what: str):
    def raise_sync(*_args, **_kwargs):
        raise HostSync(f"host sync: {what}")
    return raise_sync


class no_host_sync(TorchFunctionMode):
    """Context manager: raise :class:`HostSync` on any host-synchronising tensor op inside it."""

    def __enter__(self):
        self._saved = {name: getattr(_T, name) for name in _PATCHED}
        for name, what in _PATCHED.items():
            setattr(_T, name, _raiser(what))
        self._saved_nonzero = torch.nonzero
        torch.nonzero = _raiser("torch.nonzero")
        return super().__enter__()

    def __exit__(self, *exc):
        try:
            return super().__exit__(*exc)
        finally:
            for name, fn in self._saved.items():
                setattr(_T, name, fn)
            torch.nonzero = self._saved_nonzero

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in SYNC_OPS:
            raise HostSync(f"host sync: {SYNC_OPS[func]}")
        if func is torch.where and len(args) + len(kwargs) == 1:
            raise HostSync("host sync: torch.where(cond) (nonzero)")
        if func in (_T.__getitem__, _T.__setitem__) and len(args) > 1 and _has_bool_index(args[1]):
            raise HostSync("host sync: boolean-mask indexing")
        if func is _T.to and any(isinstance(a, (str, torch.device)) and str(a) == "cpu"
                                 for a in (*args[1:], *kwargs.values())):  # not str() of a tensor argument: a read
            raise HostSync("host sync: copy to the host")
        if func is torch.repeat_interleave and "output_size" not in kwargs and len(args) > 1 \
                and isinstance(args[1], torch.Tensor):
            raise HostSync("host sync: repeat_interleave with tensor repeats and no output_size")
        return func(*args, **kwargs)
