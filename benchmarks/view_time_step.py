"""How long `collider view` takes to redraw an animated collider when its time slider moves, on
the bending arm (examples/animations/arm.{obj,pc2}; metres, collider frame, seconds): the shipped
exact `mesh` model and a voxel one baked here (64^3, 13 keyframes), each shown with its error
colours against the interpolated mesh, on the view's default 64^3 grid (``--resolution``).

- a new time step: the slider moved to a step not seen before (the collider's distance on the
  whole grid at that time, marching cubes, error colours, the wireframe);
- a kept time step: the slider moved back to a step seen before (its grid kept).

Both kinds are measured interleaved, ROUNDS rounds of STEPS steps each, in process (the page's
own slider handler, as a browser's move calls it); median and range per step.

    python benchmarks/view_time_step.py [RESOLUTION]
"""
import os
import statistics
import sys
import time
from pathlib import Path

from collider_cli.views.collider import serve_collider_view
from collider_server.engine.modelfile import load_collider
from collider_server.making.animation_files import load_animation
from collider_server.making.bake import bake_animated_collider

ROOT = Path(__file__).resolve().parents[1]
RESOLUTION = int(sys.argv[1]) if len(sys.argv) > 1 else 64
ROUNDS, STEPS = 3, 3

animation = load_animation(ROOT / "examples/animations/arm.obj",
                           ROOT / "examples/animations/arm.pc2", 24.0, loop=True)
colliders = {"mesh (exact, shipped)": load_collider(ROOT / "models/arm.safetensors"),
             "voxel 64^3, 13 keyframes": bake_animated_collider(
                 animation, "voxel", "arm-voxel", resolution=64, keyframes=13,
                 show_progress=False)}
print(f"load average {os.getloadavg()[0]:.2f} at the start; view grid {RESOLUTION}^3")
pages = {name: serve_collider_view(c, animation, host="127.0.0.1", port=0, resolution=RESOLUTION,
                                   show_progress=False)
         for name, c in colliders.items()}
new = {name: [] for name in pages}
kept = {name: [] for name in pages}
step = next(iter(pages.values())).time.step
index = 1
for _ in range(ROUNDS):
    for name, page in pages.items():
        for i in range(index, index + STEPS):  # steps not seen before (a frame apart)
            started = time.perf_counter()
            page.time.value = (4 * i + 1) * step
            new[name].append(time.perf_counter() - started)
        for i in range(index, index + STEPS):
            page.time.value = 0.0  # t = 0: kept since the page opened
            started = time.perf_counter()
            page.time.value = (4 * i + 1) * step
            kept[name].append(time.perf_counter() - started)
    index += STEPS
for name in pages:
    for what, values in (("new time step", new[name]), ("kept time step", kept[name])):
        print(f"{name:26s} {what:15s} median {statistics.median(values) * 1e3:7.0f} ms  "
              f"range {min(values) * 1e3:.0f}-{max(values) * 1e3:.0f} ms  ({len(values)} moves)")
print(f"load average {os.getloadavg()[0]:.2f} at the end")
for page in pages.values():
    page.server.stop()
