"""How a splat file stored its vertices (:class:`PlyLayout`), kept with a splat set so that output
keeps the input's names, order and types. No Warp here: ``info`` reads layouts without it."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

# Other PLY elements that refer to vertices by row (meshes' faces and edges): a run that renumbers
# the vertices (merging, or rows dropped as invalid) would leave them pointing at the wrong splats.
_VERTEX_INDEX_PROPERTIES = {"vertex_indices", "vertex_index", "vertex1", "vertex2", "vertex"}
_VERTEX_INDEXED_ELEMENTS = {"face", "edge", "tristrips"}


@dataclass
class PlyLayout:
    """How the splats were stored in their file, so that output keeps names, order and types.

    ``properties`` lists the vertex properties in file order as (name, numpy dtype string).
    ``extra_names`` are the vertex properties that are not part of the 3DGS model; they are carried
    through a simplification in this order: the floating-point ones (:attr:`float_extra_names`) as
    ``SplatSet.extras`` columns, the integer ones (:attr:`integer_extra_names`) exactly as
    ``SplatSet.integer_extras`` columns. ``other_elements``, ``comments`` and ``obj_info`` are
    kept verbatim from the input file. ``surfels``: the file is a 2DGS one, without ``scale_2``
    (read as ``FLAT_LOG_SCALE``, :mod:`.ply_header`); an output of it is a 3DGS file, with ``scale_2``
    after ``scale_1``.
    """

    properties: list[tuple[str, str]]
    extra_names: list[str]
    other_elements: list = field(default_factory=list)
    comments: list[str] = field(default_factory=list)
    obj_info: list[str] = field(default_factory=list)
    surfels: bool = False

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

    def without_vertex_indexed(self) -> tuple[PlyLayout, str | None]:
        """This layout without the other elements that index vertices (``face``, ``edge``,
        ``tristrips`` or any element with a ``vertex_indices``-like property), and a line naming
        them (None, and the layout itself, where there are none)."""
        stale = [
            e for e in self.other_elements
            if e.name in _VERTEX_INDEXED_ELEMENTS or any(p.name in _VERTEX_INDEX_PROPERTIES for p in e.properties)
        ]  # fmt: skip
        if not stale:
            return self, None
        names = ", ".join(f"'{e.name}' ({e.count:,} rows)" for e in stale)
        return replace(self, other_elements=[e for e in self.other_elements if e not in stale]), f"dropped PLY element(s) {names}"
