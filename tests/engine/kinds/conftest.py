"""The Khronos RiggedFigure as the articulated kind's tests read it: its exact kind, the preset's
label grid, part boxes, weight field and surface anchors, and small untrained models of it.

Units: metres (the figure placed as ``collider bake ... --z-up`` places it); collider frame."""

from pathlib import Path

import pytest

FIGURE = Path(__file__).parents[2] / "data" / "gltf" / "RiggedFigure.gltf"


@pytest.fixture(scope="module")
def figure():
    """``(exact, skin, rest_sdf, anchors, mine)``: the figure's exact kind, its skin, the exact SDF
    of its rest pose, the preset's surface anchors, and ``mine`` = (labels, centre, radius,
    allowed, part boxes, weight field) in :func:`parts_through_skinning`'s order."""
    from collider_server.engine.kinds import neural_skinned as ns
    from collider_server.engine.meshes import ExactSDF, Mesh
    from collider_server.making.characters import skinned_from_file
    from collider_server.making.placement import MeshPlacement
    from collider_server.making.training.articulated import ARTICULATED_PRESET, rest_tables
    from collider_server.making.training.data import normalisation

    exact, _, _ = skinned_from_file(FIGURE, "figure", MeshPlacement(z_up=True), loop=False)
    skin = exact.skin
    rest = Mesh(skin.vertices, skin.faces, "rest")
    centre, radius = normalisation(rest, 0.1)
    labels, boxes, field, anchors = rest_tables(skin, ARTICULATED_PRESET, centre, radius)
    mine = (labels, centre, radius, ns.allowed_labels(skin.skeleton.parents, False), boxes, field)
    return exact, skin, ExactSDF(rest), anchors, mine


@pytest.fixture(scope="module")
def figure_model(figure):
    """``make(**changes)``: an untrained (seeded) small articulated model of the figure, the
    preset's map with ``changes`` to its architecture (its label grid dilated as they say)."""
    import dataclasses

    import torch

    from collider_server.engine.kinds import neural_skinned as ns
    from collider_server.making.training.articulated import ARTICULATED_PRESET

    exact, skin, _, _, mine = figure
    labels, centre, radius, _, boxes, field = mine

    def make(**changes):
        arch = dataclasses.replace(ARTICULATED_PRESET, joints=skin.skeleton.joint_count,
                                   weight_blocks=len(field.block_joints), table_log2=12, levels=4,
                                   max_resolution=64, **changes)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            network = ns.build_articulated_network(arch, centre, radius)
        grid, sets, _ = ns.dilated_labels(labels, arch.joints, arch.label_dilation)
        network.set_rest_tables(grid, sets, boxes, field)
        info = dataclasses.replace(exact.info, kind=ns.ArticulatedNeuralCollider.kind,
                                   settings={**exact.info.settings, "architecture": dataclasses.asdict(arch)})
        return ns.ArticulatedNeuralCollider(info, skin, network.eval(), device="cpu")

    return make
