"""A ``deformed`` model's rest network read through deformation fields of another resolution: the
model's own rest pose (its trained network, unchanged) with the fields refitted by
:func:`fit_deformation` at ``--deformation-resolution`` cells per side (or taken from ``--fields-of``
another deformed model of the same animation and domain), written as a new model
that ``collider eval`` measures beside the original (same points and times). What the fields'
resolution alone changes in a trained network, without training it again; metres.

    python benchmarks/refit_deformation.py out/quiet3/models/spot-bend.safetensors out/animations/spot-bend.obj \\
        out/animations/spot-bend.pc2 --deformation-resolution 32 --output out/models/spot-bend-rest15-32.safetensors
"""
import argparse
import dataclasses
import time

import numpy as np

from collider_server.engine.kinds.neural import architecture_dict
from collider_server.engine.kinds.neural_deformed import DeformedGridArchitecture
from collider_server.engine.modelfile import load_collider, save_collider
from collider_server.making.animation_files import load_animation
from collider_server.making.training import fit_deformation

parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
parser.add_argument("model", help="a deformed model (.safetensors)")
parser.add_argument("mesh", help="the OBJ it was made from")
parser.add_argument("cache", help="its vertex cache (PC2)")
fields = parser.add_mutually_exclusive_group(required=True)
fields.add_argument("--deformation-resolution", type=int, help="cells per side of the new fields")
fields.add_argument("--fields-of", help="a deformed model of the same animation whose fields to take")
parser.add_argument("--output", required=True, help="the new model (.safetensors)")
args = parser.parse_args()

model = load_collider(args.model)
arch = model.architecture
if not isinstance(arch, DeformedGridArchitecture):
    raise SystemExit(f"{args.model}: not a deformed model ({arch.encoding})")
timeline = model.info.animation
animation = load_animation(args.mesh, args.cache, timeline["frame_rate_hz"], timeline["loop"])
tensors = model.tensors()
centre, radius = np.asarray(tensors["centre"], np.float64), float(tensors["radius"])
if args.fields_of is not None:
    other = load_collider(args.fields_of)
    theirs = other.tensors()
    if not (np.array_equal(theirs["centre"], tensors["centre"]) and theirs["radius"] == tensors["radius"]
            and other.info.animation == timeline and isinstance(other.architecture, DeformedGridArchitecture)):
        raise SystemExit(f"{args.fields_of}: not a deformed model of {args.model}'s animation and domain")
    resolution, fields = other.architecture.deformation_resolution, theirs["deformation"]
else:
    started = time.perf_counter()
    resolution = args.deformation_resolution
    fit = fit_deformation(animation, centre, radius, resolution)
    print(f"{resolution}^3 fields fitted in {time.perf_counter() - started:.0f} s: they miss the frames by "
          f"{fit.summary(model.info.meters_per_unit)}")
    fields = fit.fields
new = dataclasses.replace(arch, deformation_resolution=resolution)
tensors["deformation"] = fields
# The original's measured figures are not the new model's: collider eval measures it.
info = dataclasses.replace(model.info, settings={**model.info.settings, "architecture": architecture_dict(new)},
                           accuracy={})
path = save_collider(type(model).from_tensors(info, tensors), args.output)
print(f"wrote {path} ({path.stat().st_size:,} bytes)")
