"""A module tree seen in another dtype or on another device, without changing the original.

A step takes the dtype and device of the state it is given. The scene it steps must match, but
moving the scene itself (`Module.to`) would change it for every later step: float64 constants
rounded to float32 for good, Young's modulus turned into inf by one half-precision call. A
`ConvertedMirror` instead keeps a copy of the tree whose floating tensors are converted copies of
the original's, and brings it up to date on every call: a tensor is converted again only when the
original was replaced or written into (its identity, storage or version changed), and plain
attributes (the time step, the solver, a term's settings) are read from the original each time.
The copy's modules keep their identity from call to call, so compiled evaluations keyed on the
terms are reused.

The conversions are recorded by autograd: a converted Young's modulus is a differentiable
function of the original, so gradients of a float32 step reach the float64 tensor that requires
grad.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

SUPPORTED_DTYPES = (torch.float32, torch.float64)


def check_dtype(dtype: torch.dtype, what: str) -> None:
    """Raise unless `dtype` is one the simulator computes in (float32 or float64)."""
    if dtype not in SUPPORTED_DTYPES:
        raise TypeError(
            f"{what} has dtype {dtype}; the simulator computes in float32 or float64 only: "
            "half-precision types cannot represent its constants (a Young's modulus of 1e5 Pa "
            "overflows float16) nor reach a solver's tolerance"
        )


def _listed(values: Tensor, limit: int = 5) -> str:
    items = values.reshape(-1).tolist()
    return "[" + ", ".join(f"{v:.6g}" if isinstance(v, float) else str(v) for v in items[:limit]) + (
        ", ...]" if len(items) > limit else "]"
    )


class ConvertedMirror:
    """The copy of module trees in one dtype (for floating tensors) and on one device.

    Args:
        dtype: the floating dtype of the copy, float32 or float64.
        device: the device of the copy.
    """

    def __init__(self, dtype: torch.dtype, device: torch.device) -> None:
        check_dtype(dtype, "the converted copy")
        self.dtype = dtype
        self.device = device
        # keyed by id, each with the original it was made from (an id alone may be reused)
        self._tensors: dict[int, tuple[Tensor, int, int, Tensor]] = {}
        self._modules: dict[int, tuple[nn.Module, nn.Module]] = {}

    def of(self, root: nn.Module) -> nn.Module:
        """The copy of `root`, up to date with it; `root` is not changed.

        Raises:
            ValueError: a tensor's finite or nonzero entries overflow or underflow in `dtype`; the
                message names the tensor (its path in `root`) and the entries.
        """
        tensors: dict[int, tuple[Tensor, int, int, Tensor]] = {}
        modules: dict[int, tuple[nn.Module, nn.Module]] = {}
        # recorded even under no_grad: a copy made there is reused where gradients are wanted
        with torch.enable_grad():
            copy = self._module(root, "", tensors, modules)
        # what is no longer in the tree is dropped, so replaced tensors are not kept alive
        self._tensors, self._modules = tensors, modules
        return copy

    def _module(
        self,
        module: nn.Module,
        path: str,
        tensors: dict[int, tuple[Tensor, int, int, Tensor]],
        modules: dict[int, tuple[nn.Module, nn.Module]],
    ) -> nn.Module:
        key = id(module)
        if key in modules:
            return modules[key][1]
        entry = self._modules.get(key)
        copy = entry[1] if entry is not None and entry[0] is module else type(module).__new__(type(module))
        modules[key] = (module, copy)
        state = dict(module.__dict__)
        state["_buffers"] = {
            name: self._tensor(value, path + name, tensors) for name, value in module._buffers.items()
        }
        state["_parameters"] = {
            name: self._tensor(value, path + name, tensors) for name, value in module._parameters.items()
        }
        state["_modules"] = {
            name: None if child is None else self._module(child, f"{path}{name}.", tensors, modules)
            for name, child in module._modules.items()
        }
        copy.__dict__.clear()
        copy.__dict__.update(state)
        return copy

    def _tensor(
        self, value: Tensor | None, name: str, tensors: dict[int, tuple[Tensor, int, int, Tensor]]
    ) -> Tensor | None:
        if value is None:
            return None
        key = id(value)
        entry = tensors.get(key) or self._tensors.get(key)
        if (
            entry is not None
            and entry[0] is value
            and entry[1] == value._version
            and entry[2] == value.data_ptr()
        ):
            tensors[key] = entry
            return entry[3]
        floating = value.is_floating_point()
        converted = value.to(device=self.device, dtype=self.dtype if floating else None)
        if floating and converted.dtype != value.dtype:
            self._check_representable(value, converted, name)
        tensors[key] = (value, value._version, value.data_ptr(), converted)
        return converted

    def _check_representable(self, value: Tensor, converted: Tensor, name: str) -> None:
        original = value.detach()
        back = converted.detach().to(device=original.device, dtype=original.dtype)
        overflow = torch.isfinite(original) & ~torch.isfinite(back)
        underflow = (original != 0) & (back == 0)
        for lost, how in ((overflow, "overflow to inf"), (underflow, "underflow to 0")):
            if lost.any():
                where = torch.nonzero(lost.reshape(-1)).reshape(-1)
                raise ValueError(
                    f"the scene's {name} cannot be represented in {self.dtype}: entries "
                    f"{_listed(where)} (values {_listed(original.reshape(-1)[where])}) {how}; step "
                    f"with a {original.dtype} state, or rescale the model"
                )
