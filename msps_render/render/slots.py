"""BSDF slots: the BSDF instances a worker keeps alive in one fixed layout, so that kernels repeat.

Why: drjit compiles a call through a BSDF pointer over every BSDF instance alive in the process, in
their creation order, so a frame (or a batch) whose BSDFs are new instances of another mix of kinds
compiled a new render kernel (docs/benchmarks.md "Kernels on new content").  Frames in batches
(`render.batch`) and pooled frames one at a time (`render.pool`) take their BSDFs from slots.
A BSDF's values do not depend on the slot it sits in: the pixels are the same.
"""
from __future__ import annotations

from msps_render.render.materials import baked_literals
from msps_render.render.textures import ROUGHNESS_PARAM


class BsdfSlots:
    """A worker's BSDFs in one fixed layout of drjit instances.

    Why: a call through a BSDF pointer compiles into the kernel every BSDF instance alive in the process,
    in drjit's instance order (one more unrelated BSDF alive: 12 new kernels).  A batch holds ~20 BSDFs,
    a pooled frame 2-3, of a varying mix of kinds, so each compiled (or loaded from disk) a new kernel
    for most new mixes.  Here each slot has a kind; a BSDF of kind k replaces the previous BSDF in a
    slot of kind k (the old one is freed just before the new one is made, which takes its place in
    drjit's instance order), and slots only ever grow: once a worker has seen its mix, kernels repeat.
    Slots a frame does not need keep their last BSDF alive (a few MB at most; a measured one keeps its
    table mapped)."""

    def __init__(self):
        self.slots: list[list] = []  # [kind, bsdf]

    def fill(self, wanted: list) -> list:
        """[(kind, make)] -> the BSDFs made, in that order.  Every slot to be refilled is freed first, then
        the new BSDFs are made in order, so they take the freed instance ids as the previous ones did.
        (A loop variable here once held the last slot's BSDF past its freeing: its successor took
        another id every other time, and the same mix compiled two kernels.)"""
        free: dict[str, list[int]] = {}
        for i, slot in enumerate(self.slots):  # (no name bound to a slot's BSDF: it must die when freed)
            free.setdefault(slot[0], []).append(i)
        where = []
        for kind, make in wanted:
            if free.get(kind):
                i = free[kind].pop(0)
                self.slots[i][1] = None
            else:
                i = len(self.slots)
                self.slots.append([kind, None])
            where.append((i, make))
        for i, make in where:
            self.slots[i][1] = make()
        return [self.slots[i][1] for i, _ in where]


def slot_kind(m) -> str:
    """A BSDF slot's kind (`BsdfSlots`): the material kind, what of it reads mesh attributes (texture,
    textured roughness, blend) and the values its plugin bakes in as literals (`render.materials.BAKED`,
    e.g. smooth plastic's IOR): each is other code in the kernel, so a slot never changes it."""
    rough = m.texture is not None and m.texture.roughness is not None and m.kind in ROUGHNESS_PARAM
    baked = "".join(f"@{v!r}" for v in baked_literals(m))
    return (m.kind + baked + ("+texture" if m.texture is not None else "") + ("+rough" if rough else "")
            + ("+blend" if m.blend is not None else ""))
