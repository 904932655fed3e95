"""Labels on a scatter plot that overlap no marker and no other label (matplotlib, display
coordinates): :func:`place_labels`."""

from __future__ import annotations

import numpy as np

#: Where a label may go around its marker, tried in this order at growing distances: (x, y)
#: direction of the offset, and the label's alignment there.
LABEL_SPOTS = ((0, -1, "center", "top"), (0, 1, "center", "bottom"), (1, 0, "left", "center"),
               (-1, 0, "right", "center"), (0.7, 0.7, "left", "bottom"), (0.7, -0.7, "left", "top"),
               (-0.7, 0.7, "right", "bottom"), (-0.7, -0.7, "right", "top"))


def place_labels(ax, labels: list[tuple[str, float, float, float]],
                 obstacles: list[tuple[float, float, float, str]] = ()) -> list:
    """Annotate each ``(text, x, y, marker diameter in points)`` near its marker: the first
    spot of :data:`LABEL_SPOTS`, on growing rings around the marker, where the label's rendered
    box lies inside the axes and overlaps no marker (``obstacles`` too: ``(x, y, diameter, text)``,
    a second marker of the label ``text`` names) and no label placed before; with a thin leader
    line when it had to move off the first ring or when the marker nearest it is another
    label's (clustered colliders would otherwise print over each other, or beside another marker).
    Call it once the figure's layout is final: it works in display coordinates. Returns the
    annotations."""
    fig = ax.figure
    renderer = fig.canvas.get_renderer()
    pixels_per_point = fig.dpi / 72.0

    def box(x, y, diameter):
        cx, cy = ax.transData.transform((x, y))
        r = diameter * pixels_per_point / 2
        return (cx - r, cy - r, cx + r, cy + r)

    taken = [box(x, y, d) for _, x, y, d in labels] + [box(x, y, d) for x, y, d, _ in obstacles]
    owners = [(ax.transData.transform((x, y)), text) for text, x, y, _ in labels]
    owners += [(ax.transData.transform((x, y)), text) for x, y, _, text in obstacles]

    def nearest_is_own(b, text) -> bool:
        """Whether the marker nearest the label's centre is one of its own (a reader pairs them so)."""
        centre = np.array([(b.x0 + b.x1) / 2, (b.y0 + b.y1) / 2])
        return min(owners, key=lambda o: np.hypot(*(centre - o[0])))[1] == text
    frame = ax.get_window_extent(renderer)
    annotations = []
    for text, x, y, diameter in sorted(labels, key=lambda item: item[1]):
        chosen = None
        for ring in range(6):
            gap = diameter / 2 + 3 + 12 * ring
            for ux, uy, ha, va in LABEL_SPOTS:
                arrow = {"arrowstyle": "-", "color": "grey", "linewidth": 0.6} if ring else None
                note = ax.annotate(text, (x, y), textcoords="offset points", xytext=(ux * gap, uy * gap),
                                   ha=ha, va=va, fontsize=8, arrowprops=arrow, zorder=5)
                b = text_box(note, renderer)
                inside = frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 and b.y1 <= frame.y1
                if inside and not any(b.x0 < t[2] and t[0] < b.x1 and b.y0 < t[3] and t[1] < b.y1 for t in taken):
                    chosen = note
                    break
                note.remove()
            if chosen is not None:
                break
        if chosen is None:  # nowhere free: below the marker anyway
            chosen = ax.annotate(text, (x, y), textcoords="offset points", xytext=(0, -diameter / 2 - 3),
                                 ha="center", va="top", fontsize=8, zorder=5)
        b = text_box(chosen, renderer)
        if chosen.arrow_patch is None and not nearest_is_own(b, text):  # beside another marker: tie it
            chosen.remove()
            chosen = ax.annotate(text, (x, y), textcoords="offset points", xytext=chosen.xyann,
                                 ha=chosen.get_ha(), va=chosen.get_va(), fontsize=8, zorder=5,
                                 arrowprops={"arrowstyle": "-", "color": "grey", "linewidth": 0.6})
            b = text_box(chosen, renderer)
        taken.append((b.x0, b.y0, b.x1, b.y1))
        annotations.append(chosen)
    return annotations


def text_box(note, renderer):
    """The display box of an annotation's text alone (its leader line runs to the marker)."""
    from matplotlib.text import Text

    note.update_positions(renderer)
    return Text.get_window_extent(note, renderer)
