"""Issue 34's recorded non-skinned motion, one the project's methods were not designed for: the
shipped spot cow (examples/meshes/spot.obj, metres, Y up, 1.72 m from its head at -z to its tail
at +z) bending its rear half 30 degrees sideways while translating 5 cm along x, over 2 s (25
frames at 12 fps, not looping: train and evaluate it with --clamp).

The bend: every vertex turned about the vertical axis through (0, y, ``PIVOT_Z``) by
``angle(t) * w(z)``, ``w`` a smoothstep of z over ``PIVOT_Z +- BLEND`` (the head still, the
rear turned by the whole angle), ``angle(t) = 30 deg * s(t / 2 s)`` and the shift ``5 cm *
s(t / 2 s)`` along x, ``s`` the smoothstep (starting and stopping at rest). Writes
``OUTPUT/spot-bend.obj`` (the first frame), ``OUTPUT/spot-bend.pc2`` (every frame) and
``OUTPUT/cloth_on_spot_bend.toml`` (a 0.8 x 0.8 m cloth falling from 4 cm above the cow's back
onto the part that bends, the model ``spot-bend`` placed Z up with its feet at z = 0, eps 1 mm),
then prints the commands that train, measure and drape it::

    python benchmarks/spot_bend.py --output out/spot-bend
"""
import argparse
import math
from pathlib import Path

import numpy as np

from collider_contract import Timeline
from collider_server.engine.animated_meshes import AnimatedMesh, max_surface_speed
from collider_server.making.animation_files import write_animation
from collider_server.making.mesh_files import load_mesh

ROOT = Path(__file__).resolve().parents[1]
FRAMES, FPS = 25, 12.0
BEND_DEG, SHIFT_M = 30.0, 0.05
PIVOT_Z, BLEND = 0.2, 0.3
SCENE = """# A cloth on the spot cow bending (benchmarks/spot_bend.py). World frame: metres, z up.
[scene]
name = "cloth on the bending spot"
duration_s = 2.5
dt_s = 1e-3
frame_every_steps = 25
preview_frames = [0, 40, 80, -1]

[cloth]
width = 41
height = 41
spacing_m = 2e-2
origin_m = [-0.4, -0.9, 1.097]   # over the back, 4 cm above it (the collider's y is up: +90 deg about x)
axes = "xy"
density_kg_m2 = 0.3

[[colliders]]
model = "spot-bend"
position_m = [0.0, 0.0, 0.737]
rotation_deg = [90.0, 0.0, 0.0]

[effects.gravity]
[effects.stretch]
stiffness_n_m = 20.0
[effects.shear]
stiffness_n_m = 5.0
[effects.bend]
stiffness_n_m = 0.5
[effects.damping]
coefficient_1_s = 1.0
[effects.collisions]
eps_m = 1e-3
[effects.friction]
coefficient = 0.3
"""


def smoothstep(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def spot_bend(vertices: np.ndarray) -> np.ndarray:
    """(FRAMES, V, 3) float64 metres: the bent and shifted cow at each frame."""
    weight = smoothstep((vertices[:, 2] - (PIVOT_Z - BLEND)) / (2.0 * BLEND))
    frames = np.empty((FRAMES, len(vertices), 3))
    for k in range(FRAMES):
        progress = float(smoothstep(k / (FRAMES - 1)))
        angle = math.radians(BEND_DEG) * progress * weight
        c, s = np.cos(angle), np.sin(angle)
        x, z = vertices[:, 0], vertices[:, 2] - PIVOT_Z
        frames[k, :, 0] = c * x + s * z + SHIFT_M * progress
        frames[k, :, 1] = vertices[:, 1]
        frames[k, :, 2] = -s * x + c * z + PIVOT_Z
    return frames


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", type=Path, default=Path("out/spot-bend"))
    parser.add_argument("--mesh", type=Path, default=ROOT / "examples/meshes/spot.obj")
    args = parser.parse_args()
    mesh = load_mesh(args.mesh)
    frames = spot_bend(np.asarray(mesh.vertices, np.float64))
    animation = AnimatedMesh(frames, mesh.faces, Timeline(FRAMES, FPS, False, max_surface_speed(frames, FPS)),
                             "spot-bend")
    obj, pc2 = write_animation(animation, args.output, "spot-bend")
    scene = args.output / "cloth_on_spot_bend.toml"
    scene.write_text(SCENE)
    print(f"wrote {obj}, {pc2} ({FRAMES} frames at {FPS:g} fps, {(FRAMES - 1) / FPS:g} s) and {scene}")
    print(f"collider train {obj} --animation {pc2} --fps {FPS:g} --clamp --name spot-bend --max-minutes 15 "
          "--threads 2 --models MODELS")
    print(f"collider eval spot-bend --mesh {obj} --animation {pc2} --times 16 --models MODELS")
    print(f"collider simulate {scene} --models MODELS --output OUT --check-mesh spot-bend={obj} "
          f"--check-animation spot-bend={pc2}")


if __name__ == "__main__":
    main()
