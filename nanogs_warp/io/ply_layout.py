"""How a splat file stored its vertices (:class:`PlyLayout`), kept with a splat set so that output
keeps the input's names, order and types. No Warp here: ``info`` reads layouts without it."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class PlyLayout:
    """How the splats were stored in their file, so that output keeps names, order and types.

    ``properties`` lists the vertex properties in file order as (name, numpy dtype string).
    ``extra_names`` are the vertex properties that are not part of the 3DGS model; they are carried
    through as ``SplatSet.extras`` columns in this order. ``other_elements``, ``comments`` and
    ``obj_info`` are kept verbatim from the input file.
    """

    properties: list[tuple[str, str]]
    extra_names: list[str]
    other_elements: list = field(default_factory=list)
    comments: list[str] = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)
