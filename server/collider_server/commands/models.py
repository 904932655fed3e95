"""``collider bake``, ``collider query`` and ``collider info``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..collider import FIELDS


def register(subparsers) -> None:
    bake = subparsers.add_parser("bake", help="make a voxel, mesh or kdtree collider from a mesh")
    bake.add_argument("mesh", help="mesh file (OBJ, PLY, STL, OFF, GLB)")
    bake.add_argument("--kind", choices=["voxel", "mesh", "kdtree"], default="voxel")
    bake.add_argument("--name", required=True, help="model name (file NAME.safetensors)")
    bake.add_argument("--resolution", type=int, default=256, help="voxel samples per axis (8..1024)")
    bake.add_argument("--padding", type=float, default=0.1, help="domain padding, fraction of the largest side")
    bake.add_argument("--scale", type=float, default=1.0, help="multiply mesh coordinates by this first")
    bake.add_argument("--units", default="m", help="length unit of the (scaled) mesh, e.g. m, mm")
    bake.add_argument("--meters-per-unit", type=float, default=None,
                      help="metres in one unit (derived from --units for m, cm, mm)")
    bake.add_argument("--models", type=Path, default=None, help="model repository (default: models/)")
    bake.add_argument("--device", default=None, help="cpu, cuda or auto")
    bake.add_argument("--quiet", action="store_true", help="no progress bar")
    bake.set_defaults(func=run_bake)

    query = subparsers.add_parser("query", help="distance/normal/contact of points")
    query.add_argument("model", help="model name in the repository, or a .safetensors path")
    query.add_argument("coords", nargs="*", type=float, help="x y z [x y z ...], world frame")
    query.add_argument("--points", type=Path, help=".npy file of (n, 3) points instead")
    query.add_argument("--fields", default="distance,normal,contact,collides",
                       help=f"comma-separated subset of {','.join(FIELDS)}")
    query.add_argument("--eps", type=float, default=None, help="collision offset (default 1 mm)")
    query.add_argument("--pose", type=Path, default=None, help=".npy or .json 4x4 pose, collider to world")
    query.add_argument("--output", type=Path, default=None, help="write the fields to this .npz")
    query.add_argument("--models", type=Path, default=None)
    query.add_argument("--device", default=None)
    query.set_defaults(func=run_query)

    info = subparsers.add_parser("info", help="what a model is: kind, size, domain, accuracy")
    info.add_argument("model", nargs="?", help="model name or path; omit to list the repository")
    info.add_argument("--models", type=Path, default=None)
    info.add_argument("--json", action="store_true", help="print the metadata as JSON")
    info.set_defaults(func=run_info)


UNIT_METERS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6, "km": 1000.0, "in": 0.0254, "ft": 0.3048}


def meters_per_unit(units: str, explicit: float | None) -> float:
    if explicit is not None:
        if not explicit > 0:
            raise ValueError(f"--meters-per-unit must be > 0, got {explicit}")
        return explicit
    if units not in UNIT_METERS:
        raise ValueError(f"unknown --units {units!r}; give --meters-per-unit or one of {sorted(UNIT_METERS)}")
    return UNIT_METERS[units]


def run_bake(args) -> int:
    from ..bake import bake_collider
    from ..meshes import load_mesh
    from ..modelfile import save_collider
    from ..repository import ModelRepository, check_name

    check_name(args.name)
    if not args.scale > 0:
        raise ValueError(f"--scale must be > 0, got {args.scale}")
    mesh = load_mesh(args.mesh)
    transform = np.diag([args.scale, args.scale, args.scale, 1.0])
    if args.scale != 1.0:
        mesh = mesh.transformed(transform)
    collider = bake_collider(
        mesh, args.kind, args.name, resolution=args.resolution, padding=args.padding,
        units=args.units, meters_per_unit=meters_per_unit(args.units, args.meters_per_unit),
        device=args.device, show_progress=not args.quiet,
    )
    collider.info.source["transform"] = transform.tolist()
    path = save_collider(collider, ModelRepository(args.models).path(args.name))
    print(f"wrote {path} ({path.stat().st_size:,} bytes, kind {args.kind})")
    return 0


def load_points(args) -> np.ndarray:
    if args.points is not None:
        if args.coords:
            raise ValueError("give either coordinates or --points, not both")
        try:
            return np.load(args.points, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{args.points}: cannot read points ({exc})") from None
    if not args.coords or len(args.coords) % 3:
        raise ValueError(f"give x y z triples (got {len(args.coords)} numbers) or --points FILE.npy")
    return np.asarray(args.coords, dtype=np.float64).reshape(-1, 3)


def load_pose(path: Path | None):
    if path is None:
        return None
    try:
        if path.suffix == ".json":
            return np.asarray(json.loads(path.read_text()), dtype=np.float64)
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read pose ({exc})") from None


def run_query(args) -> int:
    from ..repository import ModelRepository

    fields = [f.strip() for f in args.fields.split(",") if f.strip()]
    points = load_points(args)
    collider = ModelRepository(args.models).load(args.model, args.device)
    result = collider.query(points, fields, pose=load_pose(args.pose), eps=args.eps)
    values = result.fields()
    if args.output is not None:
        # np.savez appends ".npz" when it is missing; report the file it really writes.
        output = args.output if args.output.suffix == ".npz" else args.output.with_name(args.output.name + ".npz")
        np.savez(output, **values)
        print(f"wrote {output} ({len(points)} points)")
        return 0
    units = collider.info.units
    np.set_printoptions(precision=6, suppress=True)
    for i in range(len(points)):
        parts = [f"point {points[i].tolist()}"]
        for name, array in values.items():
            value = array[i].tolist() if array.ndim > 1 else array[i].item()
            unit = f" {units}" if name == "distance" else ""
            parts.append(f"{name}={value}{unit}")
        print("  ".join(parts))
    return 0


def run_info(args) -> int:
    from ..modelfile import read_info
    from ..repository import ModelRepository

    repo = ModelRepository(args.models)
    if args.model is None:
        names = repo.names()
        print(f"{repo.root}: {len(names)} model(s)")
        for name in names:
            size = repo.path(name).stat().st_size
            try:
                kind = read_info(repo.path(name)).kind
            except ValueError as exc:  # one damaged file must not hide the others
                kind = f"unreadable: {getattr(exc, 'problem', exc)}"
            print(f"  {name:<20} {size:>12,} bytes  {kind}")
        return 0
    path = repo.resolve(args.model)
    info = read_info(path)
    size = path.stat().st_size
    if args.json:
        json.dump({"path": str(path), "bytes": size, **info.to_dict()}, sys.stdout, indent=2)
        print()
        return 0
    print(f"{info.name}  ({path}, {size:,} bytes)")
    print(f"  kind        {info.kind}{'  (approximate)' if info.approximate else ''}")
    print(f"  units       {info.units} ({info.meters_per_unit} m per unit), collider frame")
    print(f"  domain      {np.round(info.domain_min, 6).tolist()} .. {np.round(info.domain_max, 6).tolist()}")
    source = info.source
    if source:
        print(f"  source      {source.get('mesh')} sha256 {str(source.get('sha256', ''))[:16]} "
              f"({source.get('faces', '?')} faces)")
    for key, value in info.settings.items():
        print(f"  {key:<11} {value}")
    if info.accuracy:
        print("  accuracy")
        for key, value in info.accuracy.items():
            print(f"    {key}: {value}")
    else:
        print("  accuracy    not evaluated (run `collider eval`)")
    return 0
