"""The source is MIT: nothing in it imports a GPL ("copyleft") module, such as libigl's
``igl.copyleft`` (its CGAL-based self-intersection test was replaced by
:mod:`collider_server.engine.intersections`)."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ("server", "client", "benchmarks", "scripts")


def test_no_copyleft_anywhere_in_the_source():
    hits = []
    for folder in SOURCE:
        for path in sorted((ROOT / folder).rglob("*")):
            if not path.is_file() or "__pycache__" in path.parts:
                continue
            try:
                text = path.read_text(encoding="utf-8")
            except UnicodeDecodeError:
                continue  # binary files (images, models)
            hits += [f"{path.relative_to(ROOT)}:{n}" for n, line in enumerate(text.splitlines(), 1)
                     if "copyleft" in line.lower()]
    assert not hits, "copyleft in the source: " + ", ".join(hits)
