"""`compile`: the networks a phase calls, compiled by torch.compile (inductor) in place.

`nn.Module.compile()` keeps a module's parameters and state-dict names, so checkpoints, the
optimizer and the exported model see the same module; only its calls run the compiled code.
Compiling happens on a module's first calls (each train/eval mode and grad mode its own graph),
inside the steps that make them, so the training budget pays for it. A module whose inputs change
size from step to step (packed samples) is compiled once for its first size and once more with
that size symbolic (dynamo's automatic dynamic shapes). A host read inside a network (Switch-NeRF
reads its experts' group sizes) ends a graph there: the network runs as two compiled graphs with the
read between them, in eager code.
"""

from __future__ import annotations

import torch
from torch import nn

from model.errors import Failed
from workers.toolchain import COMPILERS, cpp_compiler

COMPILED = "_leco_compiled"  # set on a module once compiled, so a later phase skips it


class CompileUnavailable(Failed):
    """`compile` was asked for on a machine that cannot compile (no C++ compiler for the CPU)."""


def check_can_compile(device: torch.device) -> None:
    """Inductor's CPU kernels are C++ it builds at run time: without a compiler the first step
    would fail deep inside torch, so the run fails first, saying what is missing."""
    if device.type != "cpu":
        return
    if cpp_compiler() is None:
        raise CompileUnavailable(
            "compile=true needs a C++ compiler on a CPU worker (inductor builds its kernels at "
            f"run time) and this machine has none ({', '.join(COMPILERS)}): install one, or "
            "train with compile=false"
        )


def compile_modules(modules: list[nn.Module]) -> int:
    """Each module compiled in place (once); how many were compiled now."""
    # imported here: it brings torch._dynamo (1.2 s), which a process that loads the training code
    # but builds no optimizer never needs; one that trains imports it with its first optimizer
    import torch._inductor.config

    # random numbers as eager code draws them (Switch-NeRF's density noise), from torch's own
    # generator: a compiled run is the eager run, and a checkpoint's RNG state resumes it
    torch._inductor.config.fallback_random = True
    compiled = 0
    for module in modules:
        if getattr(module, COMPILED, False):
            continue
        module.compile()
        setattr(module, COMPILED, True)
        compiled += 1
    return compiled
