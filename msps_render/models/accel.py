"""Where and how the network computes: device, mixed precision, memory format, pinned transfers.

One value (`Accel`) decided once per command from `--device` and the preset's `train.precision` /
`train.channels_last`, then passed to whoever moves tensors or runs the model, so no caller asks
"is this CUDA?" on its own.  Why these choices: bf16 autocast needs no loss scaler (bf16 has float32's
exponent range; on an H200 the shipped model's bf16 channels-last normals stayed within a degree of
float32's and bf16 steps trained, tests/test_accel.py, docs/benchmarks.md "GPU" -- whether it changes a
whole run's validation error is not yet measured); channels-last lets cuDNN pick tensor-core
convolution kernels; pinned host batches let the host-to-device copy overlap the previous step.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass
import torch

from msps_render.errors import InputError

def cuda_usable() -> tuple[bool, str]:
    """(usable, why not): torch sees a CUDA device and can put a tensor on it."""
    if not torch.cuda.is_available():
        built = torch.version.cuda
        return False, ("this PyTorch is a CPU build" if not built else "no CUDA device is visible to PyTorch")
    try:
        torch.zeros(1, device="cuda")
    except RuntimeError as e:  # driver too old, device busy or lost
        return False, str(e).splitlines()[0]
    return True, ""


@dataclass(frozen=True)
class Accel:
    """How tensors are placed and the model is run: `device`, `amp` (autocast dtype or None),
    `channels_last`, `pin_memory` (page-locked host batches, non-blocking copies)."""

    device: torch.device
    amp: torch.dtype | None = None
    channels_last: bool = False
    pin_memory: bool = False

    @property
    def is_cuda(self) -> bool:
        return self.device.type == "cuda"

    def describe(self) -> str:
        name = torch.cuda.get_device_name(self.device) if self.is_cuda else "CPU"
        prec = {None: "float32", torch.bfloat16: "bf16 autocast"}.get(self.amp, str(self.amp))
        return f"{self.device.type} ({name}), {prec}" + (", channels-last" if self.channels_last else "")

    def autocast(self):
        """The forward pass's mixed-precision context (a no-op in float32)."""
        if self.amp is None:
            return contextlib.nullcontext()
        return torch.autocast(self.device.type, dtype=self.amp)

    def model(self, model: torch.nn.Module) -> torch.nn.Module:
        model = model.to(self.device)
        return model.to(memory_format=torch.channels_last) if self.channels_last else model

    def tensor(self, t: torch.Tensor) -> torch.Tensor:
        """`t` on the device (4-d image tensors in channels-last when chosen)."""
        if self.pin_memory and t.device.type == "cpu":
            t = t.pin_memory()
        t = t.to(self.device, non_blocking=self.pin_memory)
        if self.channels_last and t.dim() == 4:
            t = t.contiguous(memory_format=torch.channels_last)
        return t

    def batch(self, b: dict, keys=("image", "normal", "mask", "light_dirs", "crosstalk")) -> dict:
        """A loader batch with the arrays the network reads moved to the device (the rest stay)."""
        return {**b, **{k: self.tensor(b[k]) for k in keys if k in b}}


CPU = Accel(torch.device("cpu"))


def resolve_accel(device: str = "auto", precision: str = "auto", channels_last: bool | str = "auto") -> Accel:
    """The `Accel` for `--device` (auto: CUDA when usable, else CPU) and the preset's precision.

    `--device cuda` where CUDA cannot run is one `InputError` naming the cause (no silent CPU run of a
    GPU-sized job); bf16 on the CPU is refused too (slower there, and not what was validated)."""
    if device not in ("auto", "cpu", "cuda") and not device.startswith("cuda:"):
        raise InputError("--device", f"unknown device {device!r}: use auto, cpu or cuda")
    if device == "cpu":
        dev = torch.device("cpu")
    else:
        ok, why = cuda_usable()
        if not ok and device != "auto":
            raise InputError("--device", f"{device}: CUDA is not usable here ({why}); use --device cpu")
        dev = torch.device(device if ok and device != "auto" else ("cuda" if ok else "cpu"))
    cuda = dev.type == "cuda"
    if precision == "bf16" and not cuda:
        raise InputError("train.precision", "bf16 needs a CUDA device; use fp32 (or auto) on the CPU")
    amp = torch.bfloat16 if (precision == "bf16" or (precision == "auto" and cuda)) else None
    cl = cuda if channels_last == "auto" else bool(channels_last)
    if cuda:
        torch.backends.cudnn.benchmark = True  # fixed patch shapes: autotune each convolution once
    return Accel(dev, amp, cl, pin_memory=cuda)
