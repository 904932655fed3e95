"""The shape of a grid network (:class:`GridArchitecture`): its levels, resolutions, table rows
(dense or hashed), MLP and how its table is stored. The network itself is :mod:`.neural_grid`'s."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

#: How a model file may store the feature table (``GridArchitecture.table_dtype``).
TABLE_DTYPES = ("float16", "float32", "int8", "int8-mu")


def require_integers(arch, names, least: int = 1) -> None:
    """Refuse an architecture whose fields ``names`` are not integers >= ``least`` (a bool is not
    an integer here): one ``ValueError`` naming the first such field and its value."""
    for name in names:
        value = getattr(arch, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < least:
            wanted = "a positive integer" if least == 1 else f"an integer >= {least}"
            raise ValueError(f"architecture {name} must be {wanted}, got {value!r}")


@dataclass(frozen=True)
class GridArchitecture:
    """Shape of a grid network (see the module docstring).

    levels : L, grids of growing resolution
    features : F, values per grid corner
    base_resolution, max_resolution : cells per side of the coarsest and finest grid over [-1, 1]
    table_log2 : rows per level, log2 (a level with more corners is hashed into that many rows)
    hidden_layers, hidden_width : the MLP after the encoding
    smooth : smoothstep interpolation weights (continuous normals) instead of trilinear
    surface_rows : hashed levels' rows grow like r^2 up to ``2^table_log2`` (see level_rows)
    table_dtype : how the feature table is stored in the model file: "float16", "float32",
        "int8": the hashed levels as 8-bit codes with one scale per level and feature, the dense
        (coarse) levels as float16 (see :func:`pack_table`), or "int8-mu": the same with the
        codes on a mu-law curve (finer steps near zero); computation is float32 either way
    """

    levels: int = 8
    features: int = 2
    base_resolution: int = 16
    max_resolution: int = 256
    table_log2: int = 16
    hidden_layers: int = 2
    hidden_width: int = 32
    smooth: bool = True
    table_dtype: str = "float16"
    surface_rows: bool = False
    encoding: str = "grid"
    #: The ``encoding`` of this class of architecture (a subclass has its own).
    ENCODING: ClassVar[str] = "grid"

    def __post_init__(self):
        require_integers(self, ("levels", "features", "base_resolution", "max_resolution", "table_log2",
                                "hidden_layers", "hidden_width"))
        if self.max_resolution < self.base_resolution:
            raise ValueError(f"max_resolution ({self.max_resolution}) must be >= base_resolution "
                             f"({self.base_resolution})")
        if self.table_log2 > 24:
            raise ValueError(f"table_log2 must be <= 24 (16M rows per level), got {self.table_log2}")
        if self.table_dtype not in TABLE_DTYPES:
            raise ValueError(f"table_dtype must be one of {', '.join(map(repr, TABLE_DTYPES))}, "
                             f"got {self.table_dtype!r}")
        if self.encoding != self.ENCODING:
            raise ValueError(f"a {type(self).__name__} has encoding {self.ENCODING!r}, got {self.encoding!r}")

    def grid(self) -> GridArchitecture:
        """The plain grid of this architecture (a subclass's own fields dropped): the static
        network an animated one is built on."""
        return GridArchitecture(**{f.name: getattr(self, f.name) for f in fields(GridArchitecture)
                                   if f.name != "encoding"})

    def resolutions(self) -> list[int]:
        """Cells per side of each level, coarse to fine."""
        if self.levels == 1:
            return [self.base_resolution]
        growth = (self.max_resolution / self.base_resolution) ** (1.0 / (self.levels - 1))
        return [int(round(self.base_resolution * growth ** level)) for level in range(self.levels)]

    def level_rows(self) -> list[int]:
        """Rows of each level's table: its corners when they fit (dense), else the level's hash
        table: ``2^table_log2`` rows, or with ``surface_rows`` rows growing like the number of
        cells a surface crosses (r^2), ``2^table_log2`` at the finest level, a power of two
        and at least ``2^14`` (or ``2^table_log2`` when that is smaller): the fine levels, where
        the surface detail is, get the memory. A level never has more rows than corners."""
        cap = 2 ** self.table_log2
        rows = []
        for r in self.resolutions():
            hashed = cap
            if self.surface_rows:
                share = cap * (r / self.max_resolution) ** 2
                hashed = min(cap, max(2 ** 14, 2 ** int(math.floor(math.log2(share)))))
            rows.append(min((r + 1) ** 3, hashed))
        return rows

    def level_dense(self) -> list[bool]:
        """Whether each level is dense (one row per corner) rather than hashed."""
        return [(r + 1) ** 3 <= n for r, n in zip(self.resolutions(), self.level_rows())]

    def parameter_count(self) -> int:
        width = self.levels * self.features
        mlp = 0
        for _ in range(self.hidden_layers):
            mlp += width * self.hidden_width + self.hidden_width
            width = self.hidden_width
        return sum(self.level_rows()) * self.features + mlp + width + 1
