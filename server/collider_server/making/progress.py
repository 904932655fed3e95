"""Progress bars for long work (baking, training, benchmarks, simulation), on stderr, how
durations are written in the estimates those commands print up front, and how a measured value
is written beside the threshold it is judged against."""

from __future__ import annotations

import contextlib
import sys


@contextlib.contextmanager
def progress(total: int | None, desc: str, unit: str = "it", enabled: bool = True):
    """A tqdm bar on stderr, or a do-nothing stand-in when ``enabled`` is False."""
    if not enabled:
        yield _Silent(total)
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit=unit, unit_scale=True, file=sys.stderr,
              dynamic_ncols=True, mininterval=0.5) as bar:
        yield bar


class _Silent:
    """A bar that shows nothing but counts like tqdm (``n`` of ``total``)."""

    def __init__(self, total: int | None = None):
        self.n, self.total = 0, total

    def update(self, n: int = 1) -> None:
        self.n += n

    def set_postfix(self, *args, **kwargs) -> None:
        pass

    def set_postfix_str(self, *args, **kwargs) -> None:
        pass


def format_duration(seconds: float) -> str:
    """``"45 s"``, ``"3.2 min"``, ``"2 h 31 min"``."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.1f} min"
    return f"{int(seconds // 3600)} h {int(seconds % 3600 // 60):02d} min"


def format_against(value: float, threshold: float, decimals: int = 3) -> str:
    """``value`` with at least ``decimals`` decimals, and as many more (up to 12) as it takes for
    the text to compare with ``f"{threshold:g}"`` as ``value`` compares with ``threshold``: a
    value just over its bound never reads as equal to it ("0.10003 mm, over 0.1 mm", not
    "0.100 mm, over 0.1 mm"). Both in the same units."""
    value, shown = float(value), float(f"{threshold:g}")
    want = (value > threshold) - (value < threshold)
    for places in range(decimals, 13):
        text = f"{value:.{places}f}"
        if (float(text) > shown) - (float(text) < shown) == want:
            return text
    return text
