"""``collider train`` and ``collider eval``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from .models import meters_per_unit

Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def register(subparsers) -> None:
    from ..kinds.neural import PRESETS
    from ..training import TrainConfig

    defaults = TrainConfig()
    train = subparsers.add_parser("train", help="train a neural collider from a mesh")
    train.add_argument("mesh", help="mesh file (OBJ, PLY, STL, OFF, GLB)")
    train.add_argument("--name", required=True, help="model name (file NAME.safetensors)")
    train.add_argument("--preset", default=defaults.preset, choices=sorted(PRESETS))
    train.add_argument("--samples", type=int, default=defaults.samples, help="cached training samples")
    train.add_argument("--steps", type=int, default=defaults.steps)
    train.add_argument("--batch-size", type=int, default=defaults.batch_size)
    train.add_argument("--learning-rate", type=float, default=defaults.learning_rate)
    train.add_argument("--normal-weight", type=float, default=defaults.normal_weight,
                       help="weight of the 1 - cos(normal) term (0: the paper's pure L1)")
    train.add_argument("--max-minutes", type=float, default=None, help="stop after this long (keeps the best)")
    train.add_argument("--seed", type=int, default=defaults.seed)
    train.add_argument("--threads", type=int, default=None, help="CPU threads for torch")
    train.add_argument("--scale", type=float, default=1.0, help="multiply mesh coordinates by this first")
    train.add_argument("--fit-size", type=float, default=None,
                       help="instead of --scale: scale so the largest side is this long (model units)")
    train.add_argument("--z-up", action="store_true", help="rotate a Y-up mesh to Z-up (the paper's frame)")
    train.add_argument("--units", default="m", help="length unit of the (scaled) mesh")
    train.add_argument("--meters-per-unit", type=float, default=None)
    train.add_argument("--models", type=Path, default=None, help="model repository (default: models/)")
    train.add_argument("--checkpoint", type=Path, default=None,
                       help="resumable checkpoint file (default: runs/NAME.ckpt.safetensors)")
    train.add_argument("--device", default=None, help="cpu, cuda or auto")
    train.add_argument("--quiet", action="store_true")
    train.set_defaults(func=run_train)

    evaluate = subparsers.add_parser("eval", help="measure a collider against the exact mesh SDF")
    evaluate.add_argument("model", help="model name or .safetensors path (any kind)")
    evaluate.add_argument("--mesh", required=True, help="the mesh it was made from (its original file)")
    evaluate.add_argument("--points", type=int, default=100_000, help="points per band")
    evaluate.add_argument("--seed", type=int, default=1234)
    evaluate.add_argument("--no-reconstruction", action="store_true", help="skip marching cubes")
    evaluate.add_argument("--no-save", action="store_true", help="do not write the figures into the model")
    evaluate.add_argument("--report", type=Path, default=None, help="also write the figures as JSON here")
    evaluate.add_argument("--models", type=Path, default=None)
    evaluate.add_argument("--device", default=None)
    evaluate.add_argument("--quiet", action="store_true")
    evaluate.set_defaults(func=run_eval)


def source_transform(mesh, scale: float, fit_size: float | None, z_up: bool) -> np.ndarray:
    """The 4x4 similarity applied to the mesh file's coordinates before training."""
    if not scale > 0:
        raise ValueError(f"--scale must be > 0, got {scale}")
    transform = Y_UP_TO_Z_UP.copy() if z_up else np.eye(4)
    if fit_size is not None:
        if not fit_size > 0:
            raise ValueError(f"--fit-size must be > 0, got {fit_size}")
        scale = fit_size / float(np.ptp(mesh.vertices, axis=0).max())
    return np.diag([scale, scale, scale, 1.0]) @ transform


def run_train(args) -> int:
    from ..meshes import load_mesh
    from ..modelfile import save_collider
    from ..repository import ModelRepository, check_name
    from ..training import TrainConfig, train_neural

    check_name(args.name)
    config = TrainConfig(
        preset=args.preset, samples=args.samples, steps=args.steps, batch_size=args.batch_size,
        learning_rate=args.learning_rate, normal_weight=args.normal_weight,
        max_minutes=args.max_minutes, seed=args.seed, threads=args.threads,
    )
    config.check()
    mesh = load_mesh(args.mesh)
    transform = source_transform(mesh, args.scale, args.fit_size, args.z_up)
    if not np.allclose(transform, np.eye(4)):
        mesh = mesh.transformed(transform)
    checkpoint = args.checkpoint or Path("runs") / f"{args.name}.ckpt.safetensors"
    checkpoint.parent.mkdir(parents=True, exist_ok=True)
    result = train_neural(
        mesh, args.name, config, units=args.units,
        meters_per_unit=meters_per_unit(args.units, args.meters_per_unit), transform=transform,
        device=args.device, checkpoint=checkpoint, show_progress=not args.quiet,
    )
    path = save_collider(result.collider, ModelRepository(args.models).path(args.name))
    history = checkpoint.with_name(checkpoint.name + ".history.json")
    history.write_text(json.dumps(result.history, indent=1))
    print(f"wrote {path} ({path.stat().st_size:,} bytes): {result.steps} steps in "
          f"{result.seconds / 60:.1f} min, best mean error in the +-1 mm band {result.best_validation_mm:.4f} mm")
    print(f"next: collider eval {args.name} --mesh {args.mesh}")
    return 0


def run_eval(args) -> int:
    from ..evaluation import evaluate_collider, format_report
    from ..meshes import load_mesh
    from ..modelfile import save_collider
    from ..repository import ModelRepository

    repo = ModelRepository(args.models)
    path = repo.resolve(args.model)
    collider = repo.load(args.model, args.device)
    mesh = load_mesh(args.mesh)
    transform = np.asarray(collider.info.source.get("transform", np.eye(4)), dtype=np.float64)
    if not np.allclose(transform, np.eye(4)):
        mesh = mesh.transformed(transform)
    if collider.info.source.get("sha256") and collider.info.source["sha256"] != mesh.sha256:
        # On stderr, so that stdout stays the report alone.
        print(f"collider eval: warning: {args.mesh} is not the mesh {collider.info.name} was made "
              "from (sha256 differs)", file=sys.stderr)
    report = evaluate_collider(collider, mesh, points=args.points, seed=args.seed,
                               reconstruction=not args.no_reconstruction, path=path,
                               show_progress=not args.quiet)
    print(format_report(collider.info.name, collider.info.kind, report))
    if args.report is not None:
        args.report.write_text(json.dumps(report, indent=2))
    if not args.no_save:
        collider.info.accuracy = report
        save_collider(collider, path)
        print(f"figures written into {path}")
    return 0
