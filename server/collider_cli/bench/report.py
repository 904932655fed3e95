"""What a bench report looks like to people: the paper-layout time table, the accuracy table,
ratios to the exact ``mesh`` collider, the Pareto front and the error-vs-time picture.

The parts: :mod:`.ranking` (reference times, equality, fronts), :mod:`.tables` (the text and
Markdown), :mod:`.labels` (label placement), :mod:`.plots` (the files and the picture); their
names are importable from here.
"""

from __future__ import annotations

from .labels import LABEL_SPOTS, place_labels, text_box
from .plots import figure, interrupted_line, plot, write_outputs
from .ranking import (
    BASES,
    ERROR_KEYS,
    REFERENCE_MODE,
    TIE,
    equal_times,
    front,
    front_items,
    pareto_front,
    ranking_basis,
    reference_mode,
    reference_seconds_per_point,
    reference_spread,
    reference_timing,
    timing,
    unstable_references,
)
from .tables import (
    accuracy_table,
    front_text,
    ratio_table,
    served_faster,
    size_label,
    summary,
    time_tables,
    timing_text,
)

__all__ = ["BASES", "ERROR_KEYS", "LABEL_SPOTS", "REFERENCE_MODE", "TIE", "accuracy_table", "equal_times",
           "figure", "front", "front_items", "front_text", "interrupted_line", "pareto_front", "place_labels", "plot",
           "ranking_basis", "ratio_table", "reference_mode", "reference_seconds_per_point", "reference_spread",
           "reference_timing", "served_faster", "size_label", "summary", "text_box", "time_tables",
           "timing", "timing_text", "unstable_references", "write_outputs"]
