"""How a splat file stored its vertices (:class:`PlyLayout`), kept with a splat set so that output
keeps the input's names, order and types. No Warp here: ``info`` reads layouts without it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class PlyLayout:
    """How the splats were stored in their file, so that output keeps names, order and types.

    ``properties`` lists the vertex properties in file order as (name, numpy dtype string).
    ``extra_names`` are the vertex properties that are not part of the 3DGS model; they are carried
    through a simplification in this order: the floating-point ones (:attr:`float_extra_names`) as
    ``SplatSet.extras`` columns, the integer ones (:attr:`integer_extra_names`) exactly as
    ``SplatSet.integer_extras`` columns. ``other_elements``, ``comments`` and ``obj_info`` are
    kept verbatim from the input file.
    """

    properties: list[tuple[str, str]]
    extra_names: list[str]
    other_elements: list = field(default_factory=list)
    comments: list[str] = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)

    def extra_dtype(self, name: str) -> np.dtype:
        return np.dtype(dict(self.properties).get(name, "f4"))

    def extra_dtypes(self) -> dict[str, np.dtype]:
        """Each extra property's numpy dtype (float32 where the layout does not name its type), in
        one pass over the properties: files may hold tens of thousands of them."""
        types = dict(self.properties)
        return {n: np.dtype(types.get(n, "f4")) for n in self.extra_names}

    @property
    def integer_extra_names(self) -> list[str]:
        """The extra properties of an integer type (char to uint), in file order."""
        return [n for n, t in self.extra_dtypes().items() if t.kind in "iu"]

    @property
    def float_extra_names(self) -> list[str]:
        """The other extra properties (float, double), in file order."""
        return [n for n, t in self.extra_dtypes().items() if t.kind not in "iu"]
