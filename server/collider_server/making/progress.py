"""Progress bars for long work (baking, training, benchmarks, simulation), on stderr."""

from __future__ import annotations

import contextlib
import sys


@contextlib.contextmanager
def progress(total: int | None, desc: str, unit: str = "it", enabled: bool = True):
    """A tqdm bar on stderr, or a do-nothing stand-in when ``enabled`` is False."""
    if not enabled:
        yield _Silent()
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit=unit, unit_scale=True, file=sys.stderr,
              dynamic_ncols=True, mininterval=0.5) as bar:
        yield bar


class _Silent:
    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, *args, **kwargs) -> None:
        pass

    def set_postfix_str(self, *args, **kwargs) -> None:
        pass
