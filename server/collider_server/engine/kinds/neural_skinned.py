"""The articulated neural collider (kind ``neural-skinned``): one network for a skinned character
that answers at any pose of its skeleton (a clip and a time, or the joints' transforms), as the
exact ``skinned`` kind does, from a few megabytes.

Per-part fields in each joint's rest frame, composed by a minimum (COAP-style), sharing one grid:

- **The rigid maps.** At a pose ``T`` (J, 4, 4) (the joints' world transforms, collider frame)
  joint j moves its part by ``A_j = T_j @ inverse_bind_j`` (rest pose -> posed, collider frame).
  A query point x is taken back to the rest pose as if rigidly attached to joint j:
  ``x_j = A_j^-1 x``.
- **Which parts a point may belong to** (:func:`part_candidates`): a label grid over the rest
  pose (``label_resolution``^3 cells over the grid's domain, uint8) says which joint owns each
  cell (the dominant joint of the nearest rest vertex; :data:`NO_PART` beyond a band outside the
  rest surface). Joint j is a candidate for x when the label at ``x_j`` is j itself or, with
  ``neighbours``, j's parent or one of its children (the region a bent joint's blend reaches).
  A point with no candidate (far from the body) takes the joint whose part box (the rest
  vertices it dominates, padded) is nearest to its ``x_j``. With the architecture's
  ``candidate_rule`` ``retry-labels``, a point none of whose candidates reaches a root through the
  skinning (below) is tried again with the parts the label grid names at its rigid images
  (:func:`labels_seen`); :func:`candidate_groups_through_skinning` is the rule's one home.
- **Through the skinning** (:func:`carry_to_rest`): each candidate's rigid image is carried on to
  the rest point y that linear blend skinning takes to x, ``sum_k w_k(y) A_k [y, 1] = x``, by
  damped Newton steps (:func:`newton_rest`, the architecture's ``skinning_solver`` ``newton``) or
  the first files' fixed-point steps (:func:`skinned_rest`), the weights read from the rest
  pose's :class:`WeightField` (a coarse grid and blocks of a fine one near the rest surface). The
  normal is then pulled back through that map's inverse derivative, and the velocity is the
  skinning's motion at y.
- **One shared field, conditioned per part** (:func:`build_articulated_network`): the static
  grid network of :mod:`.neural_grid` over the rest pose, evaluated at ``x_j``, whose first
  layer gets a per-part bias ``embedding_j + condition @ code_j``; ``code_j`` holds the rotations
  (relative to the rest pose, minus the identity) of joint j against its parent and of its
  children against it (:func:`pose_codes`): what bends the skin near the part. A bias of the
  first layer is all the condition is, so the fused CPU kernel of the static network answers
  all parts' points in one call, each point taking its part's first bias.
- **Composition**: ``d(x) = min_j f(x_j; j, code_j)`` over the candidates (the union of the
  parts, as the exact kind answers a self-overlapping skin); the normal is the chosen part's
  gradient through its rigid map, ``(A_j^-1)[:3, :3]^T grad f``; the surface velocity is the
  chosen part's rigid motion at the point, ``dA_j/dt @ A_j^-1 x`` (``dA_j/dt = dT_j/dt @
  inverse_bind_j``).
- **Exact patches near the skin** (:mod:`.patches`): a row the network puts within
  ``PATCH_BAND`` finest cells of the skin is answered on the posed faces around its rest closest
  point ``y - f grad f / |grad f|`` (distance, normal and velocity as the exact kind's), unless
  the patch lies farther than the network's distance plus the patches' reach; the union then
  takes the rows as before.

The model file holds the skin as the exact kind stores it (so the pose of a clip is computed by
the same code, and ``collider eval`` has its truth) plus the network's arrays under
``network.`` (the grid's table packed as the static preset's, 8-bit hashed levels).
"""

from __future__ import annotations

import math
import threading
from dataclasses import asdict, dataclass
from typing import ClassVar, NamedTuple

import numpy as np

from ..collider import Collider, ColliderInfo
from ..devices import resolve_device
from ..kept import Kept
from ..meshes import edge_index
from ..skinning import Skeleton, Skin, skin_velocities, skin_vertices
from . import grid_kernels
from .grid_architecture import require_integers
from .neural import across_plateaus
from .neural_grid import GridArchitecture, build_grid_network, pack_table, unpack_table
from .patches import (
    NEAR_CELL,
    PATCH_BAND,
    PATCH_CELL,
    PATCH_REACH,
    NearCells,
    PatchCells,
    PosedSurface,
    answer_near_first,
    answer_on_patches,
    near_points,
    patch_cells,
    pose_cells,
    posed_surface,
)
from .skinned import pose_key, resolve_pose, skin_from_tensors, skin_tensors

#: The label of a rest-pose cell no part owns (beyond the band outside the rest surface).
NO_PART = 255
#: Prefix of the network's arrays in the model file (the skin's are unprefixed).
NETWORK_PREFIX = "network."
#: How a part's rigid rest image is carried on through the skinning (:func:`carry_to_rest`).
SKINNING_SOLVERS = ("fixed-point", "newton")
#: Which parts a point may belong to (:func:`parts_through_skinning`): ``own-label`` (the first
#: files': joint j where the label at its rigid image is its own) or ``retry-labels`` (the same,
#: then, where none of a point's candidates reaches a root through the skinning, the parts the
#: label grid names at the point's rigid images are tried).
CANDIDATE_RULES = ("own-label", "retry-labels")
#: Cells per side of a block of the fine weight field (:func:`weight_field`).
BLOCK_CELLS = 4


@dataclass(frozen=True)
class ArticulatedGridArchitecture(GridArchitecture):
    """The static grid network's shape (the rest pose's field; default the ``grid`` preset's
    2^17 rows per hashed level in 8 bits) plus:

    joints : J, parts (one per joint of the skeleton)
    pose_slots : rotations in a part's pose code: its own against its parent, then up to
        ``pose_slots - 1`` children's against it (9 numbers each)
    label_resolution : cells per side of the rest pose's label grid
    neighbours : a joint is a candidate where the label is its parent's or a child's too (False:
        only where it is its own)
    label_dilation : a joint is a candidate where its rigid image lies within this many label
        cells of a cell it owns (:func:`dilated_labels`: the cells near a boundary between parts
        name every part around); 0: only in its own cells (the files before it)
    skinning_iterations : steps that carry a part's rigid rest image on through the skinning
        (:func:`carry_to_rest`); 0: rigid parts only
    skinning_solver : ``"fixed-point"`` (:func:`skinned_rest`'s steps ``x_rest <- M(x_rest)^-1 x``,
        the first model files') or ``"newton"`` (:func:`newton_rest`: damped Newton steps with the
        weight grid's derivative; a candidate that does not converge is dropped where its point
        has one that does)
    weight_resolution : cells per side of the rest pose's skinning-weight grid (its 4 largest
        weights per corner, 8 bits each)
    fine_weight_resolution : cells per side of the finer weight grid kept in blocks near the rest
        surface (:func:`weight_field`; a multiple of :data:`BLOCK_CELLS`); 0: none
    weight_blocks : how many blocks of it the model holds (set by the training)
    candidate_rule : :data:`CANDIDATE_RULES`: ``"own-label"`` (the first model files') or
        ``"retry-labels"`` (a second pass where none of a point's candidates reached a root)
    surface_offsets : the Newton map adds, near the rest surface, the pose's
        :func:`surface_offsets` (the posed mesh's flat triangles against the skinned weight field;
        needs ``fine_weight_resolution`` and the ``newton`` solver); False: the files before it
    """

    joints: int = 1
    pose_slots: int = 4
    label_resolution: int = 64
    neighbours: bool = False
    label_dilation: int = 0
    skinning_iterations: int = 2
    weight_resolution: int = 48
    skinning_solver: str = "fixed-point"
    fine_weight_resolution: int = 0
    weight_blocks: int = 0
    candidate_rule: str = "own-label"
    surface_offsets: bool = False
    table_log2: int = 17
    table_dtype: str = "int8"
    encoding: str = "articulated-grid"
    ENCODING: ClassVar[str] = "articulated-grid"

    def __post_init__(self):
        super().__post_init__()
        require_integers(self, ("joints", "pose_slots", "label_resolution", "weight_resolution"))
        require_integers(self, ("skinning_iterations", "fine_weight_resolution", "weight_blocks", "label_dilation"),
                         least=0)
        if self.fine_weight_resolution % BLOCK_CELLS:
            raise ValueError(f"architecture fine_weight_resolution must be a multiple of {BLOCK_CELLS}, "
                             f"got {self.fine_weight_resolution}")
        if self.skinning_solver not in SKINNING_SOLVERS:
            raise ValueError(f"architecture skinning_solver must be one of {', '.join(SKINNING_SOLVERS)}, "
                             f"got {self.skinning_solver!r}")
        if self.candidate_rule not in CANDIDATE_RULES:
            raise ValueError(f"architecture candidate_rule must be one of {', '.join(CANDIDATE_RULES)}, "
                             f"got {self.candidate_rule!r}")
        if self.surface_offsets and (not self.fine_weight_resolution or self.skinning_solver != "newton"):
            raise ValueError("architecture surface_offsets needs a fine_weight_resolution and the newton skinning_solver")
        if self.joints >= NO_PART:
            raise ValueError(f"an articulated network has at most {NO_PART - 1} joints, got {self.joints}")

    def code_width(self) -> int:
        return 9 * self.pose_slots

    def parameter_count(self) -> int:
        return (super().parameter_count() + self.joints * self.hidden_width
                + self.hidden_width * self.code_width())


# --------------------------------------------------------------------------------------------
# The pose: rigid maps, codes, candidates (numpy, collider frame, float64)


def rest_maps(skeleton: Skeleton, joint_transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(to_rest (J, 3, 4), to_posed (J, 4, 4))`` float64: each part's map from the posed
    collider frame back to the rest pose, ``A_j^-1`` (its last row dropped), and ``A_j = T_j @
    inverse_bind_j`` itself, for joint transforms ``T`` (J, 4, 4)."""
    posed = np.asarray(joint_transforms, np.float64) @ skeleton.inverse_bind
    return np.linalg.inv(posed)[:, :3, :], posed


def pose_codes(skeleton: Skeleton, joint_transforms: np.ndarray, slots: int) -> np.ndarray:
    """(J, 9 * slots) float32: per joint, its local rotation relative to the rest pose minus the
    identity (zero for a root: a root's rotation moves the part, it does not bend it), then its
    first ``slots - 1`` children's; zero where a joint has fewer children. Rotations are taken
    from the local transforms with their scale divided out."""
    world = np.asarray(joint_transforms, np.float64)
    parents = skeleton.parents
    above = np.where((parents >= 0)[:, None, None], world[np.maximum(parents, 0)], skeleton.root)
    local = np.linalg.solve(above, world)[:, :3, :3]
    rest = skeleton.rest_local()[:, :3, :3]
    local = local / np.linalg.norm(local, axis=1, keepdims=True)
    rest = rest / np.linalg.norm(rest, axis=1, keepdims=True)
    relative = np.swapaxes(rest, 1, 2) @ local - np.eye(3)
    relative[parents < 0] = 0.0
    relative = relative.reshape(len(parents), 9)
    codes = np.zeros((len(parents), slots, 9))
    codes[:, 0] = relative
    for j in range(len(parents)):
        for slot, child in enumerate(np.flatnonzero(parents == j)[: slots - 1]):
            codes[j, slot + 1] = relative[child]
    return codes.reshape(len(parents), -1).astype(np.float32)


def allowed_labels(parents: np.ndarray, neighbours: bool, sets: np.ndarray | None = None) -> np.ndarray:
    """(J, 256) bool: whether joint j is a candidate where the label grid says ``label``: its
    own, with ``neighbours`` its parent's and its children's, and every code of a set holding
    it (``sets`` (256, J) bool, :func:`dilated_labels`); never :data:`NO_PART`."""
    count = len(parents)
    allowed = np.zeros((count, 256), bool)
    allowed[np.arange(count), np.arange(count)] = True
    if neighbours:
        for child, parent in enumerate(parents):
            if parent >= 0:
                allowed[child, parent] = allowed[parent, child] = True
    if sets is not None:
        allowed |= sets.T
    return allowed


def dilated_labels(labels: np.ndarray, joints: int, cells: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The label grid ``labels`` (R, R, R) uint8 (:func:`part_labels`) with its boundaries widened
    by ``cells``: a labelled cell within ``cells`` cells (the 3^3, 5^3, ... block about it) of
    cells of other parts takes a code (J .. 254) that names the set of those parts and its own.
    Returns ``(labels (R, R, R) uint8, sets (256, J) bool, dropped)``: ``sets[code, j]`` says
    whether ``code`` names joint j (row j names j alone; :data:`NO_PART`'s none). The commonest
    sets get codes first; a cell whose set finds none left keeps its own label (``dropped``:
    how many cells). :data:`NO_PART` cells stay so (no part near them on the rest surface)."""
    from scipy import ndimage

    sets = np.zeros((256, joints), bool)
    sets[np.arange(joints), np.arange(joints)] = True
    if cells <= 0:
        return labels, sets, 0
    structure = np.ones((2 * cells + 1,) * 3, bool)
    near = np.zeros(labels.shape + (joints,), bool)
    for j in range(joints):
        near[..., j] = ndimage.binary_dilation(labels == j, structure)
    labelled = labels != NO_PART
    shared = labelled & (near.sum(axis=-1) > 1)
    keys, inverse, counts = np.unique(np.packbits(near[shared], axis=-1), axis=0, return_inverse=True,
                                      return_counts=True)
    order = np.argsort(-counts, kind="stable")
    free = NO_PART - joints
    code = np.full(len(keys), -1, np.int64)
    code[order[:free]] = joints + np.arange(min(free, len(keys)))
    members = np.unpackbits(keys, axis=-1, count=joints).astype(bool)
    sets[code[order[:free]]] = members[order[:free]]
    out = labels.copy()
    mine = code[inverse.reshape(-1)]
    index = np.flatnonzero(shared.reshape(-1))
    kept = mine >= 0
    out.reshape(-1)[index[kept]] = mine[kept]
    return out, sets, int((~kept).sum())


def part_candidates(points: np.ndarray, to_rest: np.ndarray, labels: np.ndarray, centre, radius: float,
                    allowed: np.ndarray, part_boxes: np.ndarray, fused: bool = True,
                    rest_boxes: np.ndarray | None = None):
    """The parts each point may belong to (the rule of the module docstring).

    points : (n, 3) float64, collider frame at the pose; to_rest : (J, 3, 4) (:func:`rest_maps`)
    labels : (R, R, R) uint8 over the cube ``centre +- radius`` (rest pose), indexed [i, j, k]
        along x, y, z; allowed : (J, 256) bool (:func:`allowed_labels`)
    part_boxes : (J, 2, 3) float64, each part's rest box (lo, hi), for points with no candidate
    fused : decide in one numba kernel over the points (:func:`_candidate_mask`) when numba is
        there; else (or False) numpy, joint by joint (the reference)
    rest_boxes : :func:`label_boxes` of ``labels`` and ``allowed`` where the caller keeps it (a
        collider: pose-independent), else computed here
    Returns ``(point (k,) int64, joint (k,) int64, rest (k, 3) float64)``: one row per candidate,
    its point's index, the joint and the point in that joint's rest frame; every point has at
    least one row; rows sorted by joint, then point.
    """
    points = np.ascontiguousarray(points, np.float64)
    centre = np.asarray(centre, np.float64)
    if fused and _candidate_mask is not None:
        mask = np.empty((len(to_rest), len(points)), np.bool_)
        rest_boxes = label_boxes(labels, centre, radius, allowed) if rest_boxes is None else rest_boxes
        reach = _posed_label_boxes(to_rest, rest_boxes, 2.0 * radius / labels.shape[0])
        _candidate_mask(points, np.ascontiguousarray(to_rest), labels, centre, float(radius), allowed,
                        np.ascontiguousarray(part_boxes, np.float64), reach, mask)
    else:
        mask = _candidate_mask_numpy(points, to_rest, labels, centre, radius, allowed, part_boxes)
    if fused and _candidate_rows is not None:
        return candidate_rows(points, to_rest, mask)
    rows_point, rows_joint, rows_rest = [], [], []
    for j in range(len(to_rest)):
        take = np.flatnonzero(mask[j])
        rows_point.append(take)
        rows_joint.append(np.full(len(take), j, np.int64))
        rows_rest.append(rigid_images(points[take], to_rest[j]))
    return np.concatenate(rows_point), np.concatenate(rows_joint), np.concatenate(rows_rest)


def rigid_images(points: np.ndarray, to_rest: np.ndarray) -> np.ndarray:
    """(m, 3) float64: points (m, 3) through one part's map ``to_rest`` (3, 4), summed in one fixed
    order, ``x m[:, 0] + y m[:, 1] + z m[:, 2] + m[:, 3]`` (elementwise, not a BLAS product: the
    numba pass :func:`_candidate_rows` sums in the same order, so both give the same bits)."""
    return points[:, 0:1] * to_rest[:, 0] + points[:, 1:2] * to_rest[:, 1] + points[:, 2:3] * to_rest[:, 2] \
        + to_rest[:, 3]


def candidate_rows(points: np.ndarray, to_rest: np.ndarray, mask: np.ndarray):
    """:func:`part_candidates`' rows from its (J, n) bool ``mask`` in one numba pass
    (:func:`_candidate_rows`: counts per joint and block of points, their prefix sums, then the
    rows written in place), ``points`` (n, 3) float64, ``to_rest`` (J, 3, 4); the rest points
    summed as :func:`rigid_images` sums them."""
    joints, n = mask.shape
    blocks = max(1, min(256, n // 4096))
    counts = np.empty((joints, blocks), np.int64)
    _candidate_counts(np.ascontiguousarray(mask), blocks, counts)
    offsets = np.concatenate([[0], np.cumsum(counts.ravel())]).astype(np.int64)
    total = int(offsets[-1])
    point, joint, rest = np.empty(total, np.int64), np.empty(total, np.int64), np.empty((total, 3))
    _candidate_rows(points, np.ascontiguousarray(to_rest, np.float64), np.ascontiguousarray(mask), blocks,
                    offsets[:-1].reshape(joints, blocks), point, joint, rest)
    return point, joint, rest


def labels_at(rest: np.ndarray, labels: np.ndarray, centre, radius: float) -> np.ndarray:
    """(m,) int64: the label grid's ``labels`` (R, R, R) over the cube ``centre +- radius`` at rest
    points ``rest`` (m, 3), :data:`NO_PART` outside the cube (numpy; :func:`_label_at` per point
    in the numba passes)."""
    resolution = labels.shape[0]
    cell = np.floor(((rest - centre) / radius + 1.0) * 0.5 * resolution).astype(np.int64)
    inside = ((cell >= 0) & (cell < resolution)).all(axis=1)
    label = np.full(len(rest), NO_PART, np.int64)
    c = cell[inside]
    label[inside] = labels[c[:, 0], c[:, 1], c[:, 2]]
    return label


def _candidate_mask_numpy(points, to_rest, labels, centre, radius, allowed, part_boxes) -> np.ndarray:
    """(J, n) bool: whether joint j is a candidate of point p (:func:`part_candidates`), numpy."""
    mask = np.zeros((len(to_rest), len(points)), bool)
    for j in range(len(to_rest)):
        mask[j] = allowed[j, labels_at(points @ to_rest[j, :, :3].T + to_rest[j, :, 3], labels, centre, radius)]
    lost = np.flatnonzero(~mask.any(axis=0))
    if len(lost):
        # Far from every part's region: the part whose rest box is nearest to the point's image.
        rest = np.einsum("jab,nb->nja", to_rest[:, :, :3], points[lost]) + to_rest[None, :, :, 3]
        gap = np.maximum(part_boxes[None, :, 0] - rest, 0.0) + np.maximum(rest - part_boxes[None, :, 1], 0.0)
        mask[np.argmin(np.einsum("nja,nja->nj", gap, gap), axis=1), lost] = True
    return mask


_candidate_mask = _label_at = None
if grid_kernels.available():
    import numba

    @numba.njit(cache=True, nogil=True, inline="always")
    def _label_at(m, x, y, z, labels, centre, radius):  # pragma: no cover
        """:func:`labels_at` of the point (x, y, z) through the map ``m`` (3, 4): its label."""
        resolution = labels.shape[0]
        ci = math.floor(((m[0, 0] * x + m[0, 1] * y + m[0, 2] * z + m[0, 3] - centre[0]) / radius + 1.0)
                        * 0.5 * resolution)
        cj = math.floor(((m[1, 0] * x + m[1, 1] * y + m[1, 2] * z + m[1, 3] - centre[1]) / radius + 1.0)
                        * 0.5 * resolution)
        ck = math.floor(((m[2, 0] * x + m[2, 1] * y + m[2, 2] * z + m[2, 3] - centre[2]) / radius + 1.0)
                        * 0.5 * resolution)
        if min(ci, cj, ck) < 0 or max(ci, cj, ck) >= resolution:
            return NO_PART
        return labels[ci, cj, ck]

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _candidate_mask(points, to_rest, labels, centre, radius, allowed, part_boxes, reach,
                        mask):  # pragma: no cover
        """:func:`_candidate_mask_numpy` in one pass over the points (numba, parallel): ``mask``
        (J, n) bool is overwritten. ``reach`` (J, 2, 3) (:func:`_posed_label_boxes`): a point outside
        joint j's box is not j's candidate, and its label is not looked up."""
        n = points.shape[0]
        joints = to_rest.shape[0]
        for p in numba.prange(n):
            x, y, z = points[p, 0], points[p, 1], points[p, 2]
            any_part = False
            for j in range(joints):
                if (x < reach[j, 0, 0] or x > reach[j, 1, 0] or y < reach[j, 0, 1] or y > reach[j, 1, 1]
                        or z < reach[j, 0, 2] or z > reach[j, 1, 2]):
                    mask[j, p] = False
                    continue
                own = allowed[j, _label_at(to_rest[j], x, y, z, labels, centre, radius)]
                mask[j, p] = own
                any_part = any_part or own
            if any_part:
                continue
            # Far from every part's region (few points): the nearest part box, only here.
            nearest, nearest_gap = 0, np.inf
            for j in range(joints):
                m = to_rest[j]
                gap = 0.0
                for a in range(3):
                    r = m[a, 0] * x + m[a, 1] * y + m[a, 2] * z + m[a, 3]
                    g = max(part_boxes[j, 0, a] - r, 0.0) + max(r - part_boxes[j, 1, a], 0.0)
                    gap += g * g
                if gap < nearest_gap:
                    nearest, nearest_gap = j, gap
            mask[nearest, p] = True


def label_boxes(labels: np.ndarray, centre, radius: float, allowed: np.ndarray) -> np.ndarray:
    """(J, 2, 3) float64: per joint j the rest-frame box (lo, hi) of the label cells where j is
    allowed (``allowed[j, label]``, :func:`allowed_labels`), padded by a cell (for the rounding of
    a rigid image near a cell's face); empty (lo > hi) where j is allowed nowhere. ``labels``
    (R, R, R) uint8 over the cube ``centre +- radius``. Pose-independent: a collider computes it
    once (:func:`_posed_label_boxes` carries it to each pose)."""
    resolution = labels.shape[0]
    # Per label value the least and greatest cell index along each axis holding it (hi -1: none).
    lo_cell, hi_cell = np.full((256, 3), resolution, np.int64), np.full((256, 3), -1, np.int64)
    _label_cell_boxes(np.ascontiguousarray(labels), lo_cell, hi_cell)
    joints = len(allowed)
    boxes = np.empty((joints, 2, 3))
    boxes[:, 0], boxes[:, 1] = np.inf, -np.inf
    cell = 2.0 * radius / resolution
    for j in range(joints):
        named = np.flatnonzero(allowed[j] & (hi_cell[:, 0] >= 0))
        if len(named):
            boxes[j, 0] = np.asarray(centre) + radius * (2.0 * lo_cell[named].min(axis=0) / resolution - 1.0) - cell
            boxes[j, 1] = np.asarray(centre) + radius * (2.0 * (hi_cell[named].max(axis=0) + 1) / resolution - 1.0) \
                + cell
    return boxes


#: Corner c of a cell at offset ``(c >> a) & 1`` along axis a (x in bit 0).
_CORNER_OFFSETS = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)])
#: The 8 corners of a box as shares of its sides.
_BOX_CORNERS = _CORNER_OFFSETS.astype(np.float64)


def _posed_label_boxes(to_rest: np.ndarray, rest_boxes: np.ndarray, pad: float) -> np.ndarray:
    """(J, 2, 3) float64: per joint j a box (lo, hi) of the posed collider frame outside which no
    point is j's candidate by its label: its rest box (:func:`label_boxes`) carried to the pose by
    ``A_j`` (the inverse of ``to_rest`` (J, 3, 4)), boxed again and padded by ``pad``; empty where
    the rest box is. What lets :func:`_candidate_mask` skip most joints' lookups."""
    joints = len(to_rest)
    affine = np.zeros((joints, 4, 4))
    affine[:, :3, :], affine[:, 3, 3] = to_rest, 1.0
    posed = np.linalg.inv(affine)[:, :3, :]
    empty = (rest_boxes[:, 0] > rest_boxes[:, 1]).any(axis=1)
    lo, hi = np.where(empty[:, None], 0.0, rest_boxes[:, 0]), np.where(empty[:, None], 0.0, rest_boxes[:, 1])
    corners = lo[:, None, :] + _BOX_CORNERS * (hi - lo)[:, None, :]
    moved = np.einsum("jcb,jab->jca", corners, posed[:, :, :3]) + posed[:, None, :, 3]
    boxes = np.stack([moved.min(axis=1) - pad, moved.max(axis=1) + pad], axis=1)
    boxes[empty, 0], boxes[empty, 1] = np.inf, -np.inf
    return boxes


_label_cell_boxes = None
if grid_kernels.available():

    @numba.njit(cache=True, nogil=True)
    def _label_cell_boxes(labels, lo, hi):  # pragma: no cover
        """Per label value of ``labels`` (R, R, R) the least (``lo`` (256, 3) int64) and greatest
        (``hi``) cell index along each axis holding it, updated in one pass over the cells."""
        r = labels.shape[0]
        for i in range(r):
            for j in range(r):
                for k in range(r):
                    value = labels[i, j, k]
                    lo[value, 0], hi[value, 0] = min(lo[value, 0], i), max(hi[value, 0], i)
                    lo[value, 1], hi[value, 1] = min(lo[value, 1], j), max(hi[value, 1], j)
                    lo[value, 2], hi[value, 2] = min(lo[value, 2], k), max(hi[value, 2], k)


def labels_seen(points: np.ndarray, to_rest: np.ndarray, labels: np.ndarray, centre, radius: float,
                fused: bool = True) -> np.ndarray:
    """(J, n) bool: whether the label grid names joint j at the rigid image ``x_k = A_k^-1 x`` of
    point p through any joint k (:data:`NO_PART` and the set codes of :func:`dilated_labels`
    name none: the retry keeps to the parts' own cells): the parts a point is tried with
    where none of its own-label candidates reached a root (``candidate_rule`` ``retry-labels``,
    :func:`parts_through_skinning`). ``points`` (n, 3) float64, collider frame at the pose; the
    rest as :func:`part_candidates`. One numba pass (:func:`_labels_seen`) when numba is there and
    ``fused``, else numpy (the reference)."""
    points = np.ascontiguousarray(points, np.float64)
    centre = np.asarray(centre, np.float64)
    if fused and _labels_seen is not None:
        seen = np.empty((len(to_rest), len(points)), np.bool_)
        _labels_seen(points, np.ascontiguousarray(to_rest, np.float64), labels, centre, float(radius), seen)
        return seen
    joints = len(to_rest)
    seen = np.zeros((joints, len(points)), bool)
    for k in range(joints):
        label = labels_at(points @ to_rest[k, :, :3].T + to_rest[k, :, 3], labels, centre, radius)
        some = np.flatnonzero(label < joints)
        seen[label[some], some] = True
    return seen


_labels_seen = None
if grid_kernels.available():

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _labels_seen(points, to_rest, labels, centre, radius, seen):  # pragma: no cover
        """:func:`labels_seen` in one pass over the points (numba, parallel): ``seen`` (J, n) bool
        is overwritten."""
        n = points.shape[0]
        joints = to_rest.shape[0]
        for p in numba.prange(n):
            for j in range(joints):
                seen[j, p] = False
            x, y, z = points[p, 0], points[p, 1], points[p, 2]
            for k in range(joints):
                label = _label_at(to_rest[k], x, y, z, labels, centre, radius)
                if label < joints:
                    seen[label, p] = True


_candidate_counts = _candidate_rows = None
if grid_kernels.available():
    import numba

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _candidate_counts(mask, blocks, counts):  # pragma: no cover
        """``counts`` (J, blocks) = the candidates of each joint in each block of points."""
        joints, n = mask.shape
        for b in numba.prange(blocks):
            lo, hi = b * n // blocks, (b + 1) * n // blocks
            for j in range(joints):
                c = 0
                for p in range(lo, hi):
                    c += mask[j, p]
                counts[j, b] = c

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _candidate_rows(points, to_rest, mask, blocks, offsets, point, joint, rest):  # pragma: no cover
        """The rows of :func:`candidate_rows`, each (joint, block) from its ``offsets`` (J, blocks)."""
        joints, n = mask.shape
        for b in numba.prange(blocks):
            lo, hi = b * n // blocks, (b + 1) * n // blocks
            for j in range(joints):
                r = offsets[j, b]
                m = to_rest[j]
                for p in range(lo, hi):
                    if mask[j, p]:
                        point[r] = p
                        joint[r] = j
                        x, y, z = points[p, 0], points[p, 1], points[p, 2]
                        for a in range(3):  # rigid_images' order
                            rest[r, a] = x * m[a, 0] + y * m[a, 1] + z * m[a, 2] + m[a, 3]
                        r += 1


#: Largest skinning weights kept per corner of the weight grid.
GRID_INFLUENCES = 4


#: The network's buffers that hold the :class:`WeightField`, in its order.
WEIGHT_FIELD_BUFFERS = ("weight_joints", "weight_values", "weight_block_index", "weight_block_joints",
                        "weight_block_values")


class WeightField(NamedTuple):
    """The rest pose's skinning weights (:func:`weight_field`): a coarse grid over the cube
    ``centre +- radius`` and, near the rest surface, blocks of a finer one.

    joints, weights : (R+1, R+1, R+1, 4) uint8, the coarse grid's corners (indexed [i, j, k] along
        x, y, z): the :data:`GRID_INFLUENCES` largest weights' joints and ``w * 255``
    block_index : (B, B, B) int32 over the cube's blocks of :data:`BLOCK_CELLS`^3 fine cells (B =
        fine resolution / 4): the block's row in the next two, or -1 (the coarse grid answers);
        (0, 0, 0) where there is no fine field
    block_joints, block_weights : (k, 5, 5, 5, 4) uint8: each stored block's fine corners, as the
        coarse grid's
    """

    joints: np.ndarray
    weights: np.ndarray
    block_index: np.ndarray
    block_joints: np.ndarray
    block_weights: np.ndarray


def _surface_weights(skin: Skin, rest_sdf, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """At rest points (n, 3) the weights of their closest rest surface point (the closest
    triangle's vertex weights blended by its barycentric coordinates), the :data:`GRID_INFLUENCES`
    largest kept: ``(joints (n, 4) uint8, w * 255 (n, 4) uint8)`` (renormalised)."""
    from ..meshes import barycentric

    _, closest, face = rest_sdf.query(points)
    tri = skin.faces[face]
    bary = barycentric(closest, skin.vertices[tri])
    dense = np.zeros((len(points), skin.skeleton.joint_count))
    rows = np.arange(len(points))
    for c in range(3):
        for k in range(skin.joints.shape[1]):
            np.add.at(dense, (rows, skin.joints[tri[:, c], k]), bary[:, c] * skin.weights[tri[:, c], k])
    if dense.shape[1] < GRID_INFLUENCES:  # fewer joints than slots: pad with zero weights
        dense = np.pad(dense, ((0, 0), (0, GRID_INFLUENCES - dense.shape[1])))
    top = np.argsort(-dense, axis=1)[:, :GRID_INFLUENCES]
    values = np.take_along_axis(dense, top, axis=1)
    top = np.where(top < skin.skeleton.joint_count, top, 0)
    values /= np.maximum(values.sum(axis=1, keepdims=True), 1e-12)
    return top.astype(np.uint8), np.clip(np.rint(values * 255), 0, 255).astype(np.uint8)


def block_corner_points(block_index: np.ndarray, centre, radius: float) -> np.ndarray:
    """(k, 5, 5, 5, 3) float64: the positions of the fine blocks' corners (collider frame, rest
    pose) in the blocks' order: their rows in ``block_index`` (B, B, B) (:class:`WeightField`'s)."""
    blocks = block_index.shape[0]
    cells = blocks * BLOCK_CELLS
    stored = np.flatnonzero(block_index.reshape(-1) >= 0)
    stored = stored[np.argsort(block_index.reshape(-1)[stored])]
    b = np.stack(np.unravel_index(stored, (blocks,) * 3), axis=1)
    local = np.stack(np.meshgrid(*(np.arange(BLOCK_CELLS + 1),) * 3, indexing="ij"), axis=-1)
    fine = b[:, None, None, None, :] * BLOCK_CELLS + local[None]
    return np.asarray(centre, np.float64) + radius * (-1.0 + 2.0 * fine / cells)


def weight_field(skin: Skin, centre, radius: float, resolution: int, fine_resolution: int = 0,
                 band: float = 0.0) -> WeightField:
    """The :class:`WeightField` of ``skin``'s rest pose over the cube ``centre +- radius``: at each
    corner the weights of its closest point on the rest surface (:func:`_surface_weights`), on a
    ``resolution``^3 grid and, where ``fine_resolution`` (a multiple of :data:`BLOCK_CELLS`; 0:
    none), in the blocks of a ``fine_resolution``^3 grid that come within ``band`` (collider
    units) of the rest surface."""
    from ..meshes import ExactSDF, Mesh

    rest_sdf = ExactSDF(Mesh(skin.vertices, skin.faces, "rest"))
    centre = np.asarray(centre, np.float64)
    side = resolution + 1
    axis = np.linspace(-1.0, 1.0, side)
    corners = centre + radius * np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    joints, weights = _surface_weights(skin, rest_sdf, corners)
    shape = (side, side, side, GRID_INFLUENCES)
    if not fine_resolution:
        empty = np.zeros((0, BLOCK_CELLS + 1, BLOCK_CELLS + 1, BLOCK_CELLS + 1, GRID_INFLUENCES), np.uint8)
        return WeightField(joints.reshape(shape), weights.reshape(shape), np.zeros((0, 0, 0), np.int32), empty,
                           empty.copy())
    if fine_resolution % BLOCK_CELLS:
        raise ValueError(f"the fine weight resolution must be a multiple of {BLOCK_CELLS}, got {fine_resolution}")
    blocks = fine_resolution // BLOCK_CELLS
    block_side = 2.0 * radius / blocks
    axis = -1.0 + (np.arange(blocks) + 0.5) * 2.0 / blocks
    middles = centre + radius * np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    distance, _, _ = rest_sdf.query(middles)
    near = np.flatnonzero(np.abs(distance) <= 0.5 * math.sqrt(3.0) * block_side + band)
    index = np.full(blocks ** 3, -1, np.int32)
    index[near] = np.arange(len(near), dtype=np.int32)
    index = index.reshape((blocks,) * 3)
    block_joints, block_weights = _surface_weights(skin, rest_sdf,
                                                   block_corner_points(index, centre, radius).reshape(-1, 3))
    block_shape = (len(near), BLOCK_CELLS + 1, BLOCK_CELLS + 1, BLOCK_CELLS + 1, GRID_INFLUENCES)
    return WeightField(joints.reshape(shape), weights.reshape(shape), index, block_joints.reshape(block_shape),
                       block_weights.reshape(block_shape))


def _cells_below(u: np.ndarray, cells: int) -> np.ndarray:
    """(m, 3) int64: the cell of a grid of ``cells`` cells per side over [-1, 1] that holds each
    point ``u`` (m, 3) (already clamped into the cube; the last cell holds its far face)."""
    return np.minimum(np.floor((u + 1.0) * 0.5 * cells).astype(np.int64), cells - 1)


def _fine_cells(u: np.ndarray, field: WeightField):
    """Where points ``u`` (m, 3) (the cube's coordinates, clamped into [-1, 1]) read the fine
    blocks: ``(fine (f,) int64 the points in a stored block, row (f,) its block's row, corner (f, 8,
    3) their 8 corners in the block, fraction (f, 3))``, the cell and fraction over all m points
    being :func:`_cells_below`'s of the fine grid."""
    cells = field.block_index.shape[0] * BLOCK_CELLS
    cell = _cells_below(u, cells)
    b = cell // BLOCK_CELLS
    row = field.block_index[b[:, 0], b[:, 1], b[:, 2]]
    fine = np.flatnonzero(row >= 0)
    corner = (cell[fine] - b[fine] * BLOCK_CELLS)[:, None, :] + _CORNER_OFFSETS[None]
    return fine, row[fine], corner, ((u + 1.0) * 0.5 * cells - cell)[fine]


def _trilinear(t: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 8 corners' trilinear weights (m, 8) at fractions ``t`` (m, 3) and their derivatives
    (m, 8, 3) along the axes (``scale`` (m, 3): d(fraction)/d(position))."""
    o = _CORNER_OFFSETS[None]
    f = np.where(o == 1, t[:, None, :], 1.0 - t[:, None, :])
    g = np.where(o == 1, 1.0, -1.0) * scale[:, None, :]
    weight = f[..., 0] * f[..., 1] * f[..., 2]
    return weight, np.stack([g[..., 0] * f[..., 1] * f[..., 2], f[..., 0] * g[..., 1] * f[..., 2],
                             f[..., 0] * f[..., 1] * g[..., 2]], axis=-1)


def _corner_tables(rest: np.ndarray, field: WeightField, centre, radius: float):
    """Where rest points (m, 3) read the weight field: per point its 8 corners' joints and ``w *
    255`` ((m, 8, 4) uint8 each, corner c at offset ``((c >> a) & 1)`` along axis a), the fraction
    along each axis (m, 3) and d(fraction)/d(rest) (m, 3) (0 where clamped into the cube). The
    numpy reference of :func:`_weight_source`."""
    u = (np.asarray(rest, np.float64) - centre) / radius
    clamped = (u < -1.0) | (u > 1.0)
    u = np.clip(u, -1.0, 1.0)
    cells = field.joints.shape[0] - 1
    cell = _cells_below(u, cells)
    t, scale = (u + 1.0) * 0.5 * cells - cell, np.where(clamped, 0.0, 0.5 * cells / radius)
    corner = cell[:, None, :] + _CORNER_OFFSETS[None]
    joints = field.joints[corner[..., 0], corner[..., 1], corner[..., 2]]
    weights = field.weights[corner[..., 0], corner[..., 1], corner[..., 2]]
    if field.block_index.shape[0]:
        fine, row, c, fine_t = _fine_cells(u, field)
        r = row[:, None]
        joints[fine] = field.block_joints[r, c[..., 0], c[..., 1], c[..., 2]]
        weights[fine] = field.block_weights[r, c[..., 0], c[..., 1], c[..., 2]]
        t[fine] = fine_t
        scale[fine] = np.where(clamped[fine], 0.0, 0.5 * field.block_index.shape[0] * BLOCK_CELLS / radius)
    return joints, weights, t, scale


def weight_cells(rest: np.ndarray, field: WeightField, centre, radius: float) -> np.ndarray:
    """(m, 3) or (m, 6) int64: the cell of the weight grid (then of the fine grid, where the field
    has blocks) that holds each rest point (m, 3), clamped into the cube: two points in the same
    cells read the same 8 corners, so the field is one trilinear polynomial between them."""
    u = np.clip((np.asarray(rest, np.float64) - centre) / radius, -1.0, 1.0)
    sides = [field.joints.shape[0] - 1, field.block_index.shape[0] * BLOCK_CELLS]
    return np.concatenate([_cells_below(u, cells) for cells in sides if cells], axis=1)


def weights_at(rest: np.ndarray, field: WeightField, centre, radius: float, joints: int) -> np.ndarray:
    """(m, J) float64 skinning weights at rest-pose points ``rest`` (m, 3): the weight field
    (:func:`weight_field`) interpolated trilinearly (clamped into the cube), rows summing to 1."""
    return weights_and_gradient(rest, field, centre, radius, joints)[0]


def weights_and_gradient(rest: np.ndarray, field: WeightField, centre, radius: float,
                         joints: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`weights_at` (m, J) and its derivative along the rest frame's axes (m, J, 3) float64
    (per collider unit; zero along an axis where the point is clamped into the cube)."""
    corner_joints, corner_weights, t, scale = _corner_tables(rest, field, centre, radius)
    m = len(t)
    raw = np.zeros((m, joints))
    draw = np.zeros((m, joints, 3))
    rows = np.arange(m)
    trilinear, derivative = _trilinear(t, scale)
    for corner in range(8):
        tw, dtw = trilinear[:, corner], derivative[:, corner]
        jj, ww = corner_joints[:, corner], corner_weights[:, corner] / 255.0
        for slot in range(GRID_INFLUENCES):
            np.add.at(raw, (rows, jj[:, slot]), tw * ww[:, slot])
            np.add.at(draw, (rows, jj[:, slot]), dtw * ww[:, slot, None])
    total = np.maximum(raw.sum(axis=1), 1e-12)
    w = raw / total[:, None]
    dw = (draw - w[:, :, None] * draw.sum(axis=1)[:, None, :]) / total[:, None, None]
    return w, dw


def skinning_jacobian(rest: np.ndarray, posed: np.ndarray, w: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """(m, 3, 3) float64: the derivative of linear blend skinning's map ``y -> sum_k w_k(y) A_k
    [y, 1]`` at rest points ``rest`` (m, 3), ``A = posed`` (J, 4, 4), the weights ``w`` (m, J)
    and their derivative ``dw`` (m, J, 3) (:func:`weights_and_gradient`)."""
    homogeneous = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    moved = np.einsum("jab,mb->mja", posed[:, :3, :], homogeneous)
    return np.einsum("mj,jab->mab", w, posed[:, :3, :3]) + np.einsum("mja,mjc->mac", moved, dw)


class SurfaceAnchors(NamedTuple):
    """Each fine block corner's closest rest surface point (:func:`surface_anchors`), the blocks'
    corners flattened (k * 125 rows, a block's 5^3 corners in C order): ``triangle`` (n, 3) int32
    its face's vertices, ``bary`` (n, 3) float64 its barycentric coordinates there."""

    triangle: np.ndarray
    bary: np.ndarray


def surface_anchors(skin: Skin, field: WeightField, centre, radius: float) -> SurfaceAnchors:
    """:class:`SurfaceAnchors` of ``field``'s fine blocks on ``skin``'s rest surface: the closest
    points :func:`weight_field` took their weights from (pose-independent; a model computes them
    when it loads, 0.3-0.6 s for 113,000-160,000 corners)."""
    from ..meshes import ExactSDF, Mesh, barycentric

    corners = block_corner_points(field.block_index, centre, radius).reshape(-1, 3)
    _, closest, face = ExactSDF(Mesh(skin.vertices, skin.faces, "rest")).query(corners)
    triangle = skin.faces[face]
    return SurfaceAnchors(triangle.astype(np.int32), barycentric(closest, skin.vertices[triangle]))


def surface_offsets(anchors: SurfaceAnchors, field: WeightField, skin: Skin, maps: np.ndarray,
                    fused: bool = True) -> np.ndarray:
    """(..., k, 5, 5, 5, 3) float64: at each fine block corner, the posed mesh's point of its
    anchor (the barycentric blend of its face's skinned vertices: the flat posed triangle) minus
    the anchor skinned by the corner's own weights (the weight field's map there), for ``maps``
    (..., J, 3, 4): ``A`` at a pose (an offset, collider units) or ``dA/dt`` (its velocity, per
    second); linear in the maps (several sets, e.g. a pose's and its motion's, in one pass).
    Blended trilinearly and added to the map near the surface (the architecture's
    ``surface_offsets``), they carry the rest surface onto the posed triangles where skinning a
    face's inside bends it off them, and absorb the weights' 8-bit rounding (docs/neural.md). One
    numba pass over the corners (:func:`_offsets_kernel`, 2 ms for the walker's 113,000) when
    numba is there, else numpy."""
    maps = np.asarray(maps, np.float64)
    batch = maps.shape[:-3]
    maps = np.ascontiguousarray(maps.reshape((-1,) + maps.shape[-3:]))
    joints = field.block_joints.reshape(-1, GRID_INFLUENCES)
    weights = field.block_weights.reshape(-1, GRID_INFLUENCES)
    shape = batch + field.block_joints.shape[:4] + (3,)
    if fused and _offsets_kernel is not None:
        out = np.empty((len(maps), len(joints), 3))
        _offsets_kernel(skin.vertices, np.ascontiguousarray(skin.joints, np.int64), skin.weights, anchors.triangle,
                        anchors.bary, joints, weights, maps, out)
        return out.reshape(shape)
    vertices = np.concatenate([skin.vertices, np.ones((len(skin.vertices), 1))], axis=1)
    moved = np.einsum("vk,mvkab,vb->mva", skin.weights, maps[:, skin.joints], vertices)  # the skin under the maps
    flat = np.einsum("ci,mcia->mca", anchors.bary, moved[:, anchors.triangle])
    point = np.einsum("ci,cia->ca", anchors.bary, vertices[anchors.triangle])
    q = weights / 255.0
    skinned = np.einsum("cs,mcsab,cb->mca", q, maps[:, joints], point) / np.maximum(q.sum(axis=1), 1e-12)[:, None]
    return (flat - skinned).reshape(shape)


def offsets_at(rest: np.ndarray, offsets: np.ndarray, field: WeightField, centre,
               radius: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`surface_offsets`' table ``offsets`` (k, 5, 5, 5, 3) blended trilinearly at rest
    points (m, 3), and its derivative (m, 3, 3) (d offset_a / d rest_b): zero outside the fine
    blocks (and along an axis where the point is clamped into the cube). numpy; the Newton
    kernel blends the same corners."""
    u = (np.asarray(rest, np.float64) - centre) / radius
    clamped = (u < -1.0) | (u > 1.0)
    fine, row, corner, t = _fine_cells(np.clip(u, -1.0, 1.0), field)
    scale = np.where(clamped[fine], 0.0, 0.5 * field.block_index.shape[0] * BLOCK_CELLS / radius)
    weight, derivative = _trilinear(t, scale)
    table = offsets[row[:, None], corner[..., 0], corner[..., 1], corner[..., 2]]  # (f, 8, 3)
    value, gradient = np.zeros((len(u), 3)), np.zeros((len(u), 3, 3))
    value[fine] = np.einsum("fc,fca->fa", weight, table)
    gradient[fine] = np.einsum("fcb,fca->fab", derivative, table)
    return value, gradient


#: Channels of :func:`blended_blocks`' table per map set: the map's 3 x 4 entries, the weights'
#: sum, the offset.
BLENDED_CHANNELS = 16


def blended_blocks(field: WeightField, maps: np.ndarray, offsets: np.ndarray | None = None,
                   fused: bool = True) -> np.ndarray:
    """(k, 5, 5, 5, 16 S) float64: at each corner of the weight field's fine blocks, for each of S
    map sets ``maps`` (S, J, 3, 4) (a pose's ``A``, its motion ``dA/dt``), the set blended by the
    corner's raw weights (``sum_s q_s maps[j_s]``, 3 x 4 row-major, ``q = w * 255 / 255`` as
    stored), their sum ``sum_s q_s`` and the corner's ``offsets`` (S, k, 5, 5, 5, 3) of the set
    (:func:`surface_offsets`; zero where None): channels ``16 i`` .. ``16 i + 15`` for set i.
    Trilinear in a cell, these give the Newton terms (:func:`newton_rest`'s ``F`` and ``J_F``) and
    the velocity with one contiguous read per corner, where the joints' weights need a sum per
    joint (the Newton kernel takes them for a pass of :data:`NEWTON_TABLE_ROWS` rows or more; the
    sets side by side: the velocity's read is next to the map's). One numba pass when numba is
    there and ``fused``, else numpy."""
    maps = np.ascontiguousarray(maps, np.float64)
    corners = (field.block_joints.shape[0],) + (BLOCK_CELLS + 1,) * 3
    if offsets is None:
        offsets = np.zeros((len(maps),) + corners + (3,))
    if fused and _blend_table_kernel is not None:
        out = np.empty(corners + (BLENDED_CHANNELS * len(maps),))
        _blend_table_kernel(field.block_joints.reshape(-1, GRID_INFLUENCES),
                            field.block_weights.reshape(-1, GRID_INFLUENCES), maps,
                            np.ascontiguousarray(offsets, np.float64).reshape(len(maps), -1, 3),
                            out.reshape(-1, out.shape[-1]))
        return out
    q = field.block_weights / 255.0
    sets = []
    for each, offset in zip(maps, offsets):
        blend = np.einsum("...s,...sab->...ab", q, each[field.block_joints])
        sets += [blend.reshape(corners + (12,)), q.sum(axis=-1, keepdims=True), offset]
    return np.concatenate(sets, axis=-1)


def pose_table(field: WeightField, posed: np.ndarray, moving: np.ndarray | None = None,
               offsets: np.ndarray | None = None, moving_offsets: np.ndarray | None = None) -> np.ndarray:
    """(k, 5, 5, 5, 16 or 32) float64: the Newton pass's :func:`blended_blocks` table of a pose,
    ``posed`` (J, 4, 4) with its ``offsets``, then where ``moving`` (J, 3, 4) is given the motion
    with ``moving_offsets`` beside it (:func:`carried_rows`' arguments)."""
    sets, set_offsets = [posed[:, :3, :]], [offsets]
    if moving is not None:
        sets.append(moving)
        set_offsets.append(moving_offsets)
    if offsets is None:
        return blended_blocks(field, np.stack(sets))
    return blended_blocks(field, np.stack(sets), np.stack([np.zeros_like(offsets) if o is None else o
                                                           for o in set_offsets]))


def uses_table(rows: int, field: WeightField) -> bool:
    """Whether a Newton pass of ``rows`` rows reads the fine blocks through the pose's table
    (:func:`pose_table`): :data:`NEWTON_TABLE_ROWS` or more, a fine field, the numba pass."""
    return rows >= NEWTON_TABLE_ROWS and field.block_joints.shape[0] > 0 and _newton_kernel is not None


#: Newton steps stop where the skinned rest point is this close to the query point, a share of the
#: grid's half side (the walker's 0.95 m: about 1 micrometre).
NEWTON_TOLERANCE = 1e-6
#: The longest Newton step, a share of the grid's half side (the walker: 5 cm, about a weight-grid
#: cell), and how often a step that does not lower |F| is halved before the point stops.
NEWTON_MAX_STEP = 0.05
NEWTON_HALVINGS = 4
#: A Newton step no longer than this share of the grid's half side (the walker: 95 um) is taken
#: without evaluating the map after it, and the point counts as converged: Newton's error after a
#: step is of the order of the step's square over the weights' blend (25 mm on the walker: under
#: 0.4 um here), and the map's linear part and the weights stay those before the step (the
#: gradient's pull-back and the velocity: changed by about the step over the blend, 0.4 %). Only
#: within a cell of the weights: across a cell face their derivative jumps (a step across one
#: missed the root by up to 29 um). It saves the last evaluation of most rows (docs/neural.md).
NEWTON_LAST_STEP = 1e-4


def _newton_terms(y: np.ndarray, x: np.ndarray, posed: np.ndarray, weights, offset=None):
    """``(F (m, 3), J_F (m, 3, 3))`` of :func:`newton_rest`'s equation at rest points ``y``."""
    w, dw = weights(y)
    homogeneous = np.concatenate([y, np.ones((len(y), 1))], axis=1)
    f = np.einsum("mj,jab,mb->ma", w, posed[:, :3, :], homogeneous) - x
    jacobian = skinning_jacobian(y, posed, w, dw)
    if offset is not None:
        value, gradient = offset(y)
        f, jacobian = f + value, jacobian + gradient
    return f, jacobian


def newton_rest(points: np.ndarray, rest: np.ndarray, posed: np.ndarray, weights, iterations: int,
                max_step: float = NEWTON_MAX_STEP, tolerance: float = NEWTON_TOLERANCE,
                last_step: float = 0.0, cells=None, offset=None):
    """Rest-pose images of posed points ``points`` (m, 3) through the skinning by damped Newton
    steps on ``F(y) = sum_k w_k(y) A_k [y, 1] (+ offset(y)) - x = 0`` (SNARF's root search) from
    ``rest`` (m, 3) (a part's rigid image), ``A = posed`` (J, 4, 4), ``weights(y) -> (w (m, J),
    dw (m, J, 3))`` (:func:`weights_and_gradient`), ``offset(y) -> (value (m, 3), derivative (m,
    3, 3))`` or None (:func:`offsets_at`): each step ``-J_F^-1 F``, at most ``max_step`` long, halved
    up to :data:`NEWTON_HALVINGS` times until |F| falls (else the point stops); a step no longer
    than ``last_step`` that stays in its cell of the weights, ``cells(y) -> (m, k)`` int
    (:func:`weight_cells`; given with any ``last_step`` > 0), is taken without evaluating the map
    after it (:data:`NEWTON_LAST_STEP`).
    Returns ``(rest (m, 3), inverse (m, 3, 3), converged (m,) bool)``: the images, ``J_F^-1`` at
    each row's last evaluation (the gradient's pull-back) and whether |F| <= ``tolerance`` there or
    the last step was that short. The numpy reference of :func:`_newton_kernel`."""
    x = np.asarray(points, np.float64)
    y = np.array(rest, np.float64)
    f, jacobian = _newton_terms(y, x, posed, weights, offset)
    size = np.linalg.norm(f, axis=1)  # |F| and J_F at each row's last evaluation
    converged = size <= tolerance
    active = np.flatnonzero(~converged)
    for _ in range(iterations):
        if not len(active):
            break
        step = -np.linalg.solve(jacobian[active], f[active][..., None])[..., 0]
        length = np.linalg.norm(step, axis=1)
        # A short step that stays in its cell is taken without a new evaluation (NEWTON_LAST_STEP).
        short = length <= last_step
        short[short] = (cells(y[active[short]]) == cells(y[active[short]] + step[short])).all(axis=1)
        y[active[short]] += step[short]
        converged[active[short]] = True
        active, step, length = active[~short], step[~short], length[~short]
        step *= np.minimum(1.0, max_step / np.maximum(length, 1e-300))[:, None]
        todo = np.arange(len(active))
        for _ in range(NEWTON_HALVINGS + 1):
            rows = active[todo]
            trial = y[rows] + step[todo]
            f_trial, jacobian_trial = _newton_terms(trial, x[rows], posed, weights, offset)
            size_trial = np.linalg.norm(f_trial, axis=1)
            better = size_trial < size[rows]
            moved = rows[better]
            y[moved], f[moved], jacobian[moved], size[moved] = (trial[better], f_trial[better],
                                                                jacobian_trial[better], size_trial[better])
            todo = todo[~better]
            step[todo] *= 0.5
        active = np.setdiff1d(active, active[todo])  # no step lowered |F|: stuck
        done = size[active] <= tolerance
        converged[active[done]] = True
        active = active[~done]
    return y, np.linalg.inv(jacobian), converged


def blend_at(rest: np.ndarray, maps: np.ndarray, field, centre, radius: float,
             fused: bool = True) -> np.ndarray:
    """(m, 3, 4) float64: ``sum_k w_k(x) maps_k`` at rest-pose points ``rest`` (m, 3), the
    weights :func:`weights_at`'s, ``maps`` (J, 3, 4) (the skinning's map at a pose: ``A``; its
    motion: ``dA/dt``). One numba pass (:func:`_blend_kernel`) when numba is there, else numpy."""
    rest = np.ascontiguousarray(rest, np.float64)
    maps = np.ascontiguousarray(maps, np.float64)
    if fused and _blend_kernel is not None:
        out = np.empty((len(rest), 3, 4))
        _blend_kernel(rest, maps, *field, np.asarray(centre, np.float64), float(radius), out)
        return out
    w = weights_at(rest, field, centre, radius, len(maps))
    return np.einsum("mj,jab->mab", w, maps)


def skinned_rest(points: np.ndarray, rest: np.ndarray, posed: np.ndarray, field, centre,
                 radius: float, iterations: int, fused: bool = True):
    """Rest-pose images of posed points through the skinning: from a part's rigid image ``rest``
    (m, 3), ``iterations`` fixed-point steps ``x_rest <- M(x_rest)^-1 x`` with ``M = sum_k w_k(x_rest)
    A_k`` (linear blend skinning's map at the rest point, ``A = posed`` (J, 4, 4), the weights
    :func:`weights_at`'s). Returns ``(rest (m, 3), to_rest (m, 3, 3))``: the images and the
    linear part of the last ``M^-1`` (the gradient's pull-back: the weights' own variation is
    left out). With 0 iterations the rigid image, and ``to_rest`` None (its part's map). One
    numba pass (:func:`_skinned_rest_kernel`) when numba is there and ``fused``, else numpy."""
    if iterations == 0:
        return rest, None
    points = np.ascontiguousarray(points, np.float64)
    if fused and _skinned_rest_kernel is not None:
        rest = np.array(rest, np.float64, order="C")  # moved in place
        inverse = np.empty((len(rest), 3, 3))
        _skinned_rest_kernel(points, rest, np.ascontiguousarray(posed[:, :3, :]), *field,
                             np.asarray(centre, np.float64), float(radius), iterations,
                             np.empty((len(rest), 3, 4)), inverse)
        return rest, inverse
    for _ in range(iterations):
        blend = blend_at(rest, posed[:, :3, :], field, centre, radius, fused)
        inverse = np.linalg.inv(blend[:, :, :3])
        rest = np.einsum("mab,mb->ma", inverse, points - blend[:, :, 3])
    return rest, inverse


#: A point whose fixed-point steps moved it further than this share of the grid's half side from
#: its part's rigid image (the steps diverged where the blended map nearly folds) keeps the rigid
#: image: its error is then the blend's, not a wild point's (the walker: 224 mm at worst before).
DIVERGED = 0.25


def carry_to_rest(points: np.ndarray, point: np.ndarray, joint: np.ndarray, rigid: np.ndarray,
                  to_rest: np.ndarray, posed: np.ndarray, field, centre, radius: float,
                  iterations: int, solver: str = "fixed-point", fused: bool = True,
                  offsets: np.ndarray | None = None):
    """Each candidate's rest-pose point and the linear part of its map there: candidates
    ``point`` (m,) (indices into ``points`` (n, 3), the posed points), ``joint`` (m,), their
    parts' rigid images ``rigid`` (m, 3) (``to_rest`` (J, 3, 4) of :func:`rest_maps`), carried on
    by ``solver`` (:data:`SKINNING_SOLVERS`): :func:`skinned_rest`, whose rows keep the rigid image
    and map where the steps diverged (:data:`DIVERGED`), or :func:`newton_rest` through the weight
    grid (tolerance and longest step shares of ``radius``), whose rows that did not converge are
    dropped where their point has one that did (else they keep the rigid image and map where they
    went further than :data:`DIVERGED`). The rule both the query and the training use
    (:func:`carried_rows`, which keeps every row and says which count).

    Returns ``(keep (k,) int64, rest (k, 3), inverse (k, 3, 3))``: the candidates kept (indices
    into the m rows, in order), their rest points and the linear maps that pull a rest-frame
    gradient back to the posed frame (``grad_x = inverse^T grad_rest``)."""
    carried = carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, iterations, solver,
                           fused, offsets=offsets)
    keep = np.flatnonzero(carried.usable)
    if len(keep) == len(point):  # nothing dropped: no copies of the rows
        return keep, carried.rest, carried.inverse
    return keep, carried.rest[keep], carried.inverse[keep]


class CarriedRows(NamedTuple):
    """:func:`carried_rows`' answer for m candidate rows: ``usable`` (m,) bool (the rows
    :func:`carry_to_rest` keeps), ``rest`` (m, 3) and ``inverse`` (m, 3, 3) float64 (as
    :func:`carry_to_rest`'s, for every row), ``velocity`` (m, 3) float64 or None: the skinning's
    motion at each rest point, ``sum_k w_k(rest) dA_k/dt @ [rest, 1]`` (collider units per second),
    where ``moving`` was given and the solver's pass had the weights there at hand (the Newton
    kernel); else None (:func:`blend_at` then); ``converged`` (m,) bool: the rows that reached a
    root (every row of the fixed-point steps and of rigid parts)."""

    usable: np.ndarray
    rest: np.ndarray
    inverse: np.ndarray
    velocity: np.ndarray | None
    converged: np.ndarray


def carried_rows(points: np.ndarray, point: np.ndarray, joint: np.ndarray, rigid: np.ndarray,
                 to_rest: np.ndarray, posed: np.ndarray, field, centre, radius: float, iterations: int,
                 solver: str = "fixed-point", fused: bool = True, moving: np.ndarray | None = None,
                 offsets: np.ndarray | None = None, moving_offsets: np.ndarray | None = None,
                 table: np.ndarray | None = None) -> CarriedRows:
    """:func:`carry_to_rest`'s rule without dropping rows (the query's: no copies of the rows) and,
    with ``moving`` (J, 3, 4) (``dA_j/dt``, :meth:`ArticulatedNeuralCollider.pose`), the velocity
    at each row's rest point from the Newton kernel's last weights (:class:`CarriedRows`). With
    ``offsets`` (:func:`surface_offsets` of the pose's maps; the Newton solver only), the map
    adds them, and the velocity ``moving_offsets`` (of ``moving``). ``table``: the pose's
    :func:`pose_table` of these (with the motion where ``moving`` is given), read by the Newton
    pass in the fine blocks; None: the pass builds one where :func:`uses_table` says."""
    m = len(point)
    if iterations == 0:
        return CarriedRows(np.ones(m, bool), rigid, to_rest[joint, :, :3], None, np.ones(m, bool))
    velocity = None
    if solver == "fixed-point":
        x = np.ascontiguousarray(points[point], np.float64)
        rest, inverse = skinned_rest(x, rigid, posed, field, centre, radius, iterations, fused)
        converged = np.ones(m, bool)
        moved = rest - rigid
        wild = np.flatnonzero(np.einsum("ma,ma->m", moved, moved) > (DIVERGED * radius) ** 2)
        del moved
    else:
        rest, inverse, converged, velocity, wild = _newton_through_grid(points, point, rigid, posed, field, centre,
                                                                        radius, iterations, fused, moving, offsets,
                                                                        moving_offsets, table)
    if len(wild):
        rest[wild], inverse[wild] = rigid[wild], to_rest[joint[wild], :, :3]
        if velocity is not None:  # the rigid image's own blend (rare)
            velocity[wild] = _velocity_at(rigid[wild], moving, field, centre, radius, moving_offsets, fused)
    if converged.all():
        return CarriedRows(converged, rest, inverse, velocity, converged)
    has_converged = np.zeros(len(points), bool)
    has_converged[point[converged]] = True
    return CarriedRows(converged | ~has_converged[point], rest, inverse, velocity, converged)


def _velocity_at(rest: np.ndarray, moving: np.ndarray, field, centre, radius: float,
                 moving_offsets: np.ndarray | None = None, fused: bool = True) -> np.ndarray:
    """(m, 3) float64: the skinning's motion ``sum_k w_k(y) dA_k/dt @ [y, 1]`` at rest points
    ``rest`` (m, 3) (:func:`blend_at` of ``moving`` (J, 3, 4)), plus the blended
    ``moving_offsets`` where given (:func:`surface_offsets` of ``moving``). One numba pass
    (:func:`_velocity_kernel`; the rows a Newton pass gave up on can be most of a retry's) when
    numba is there and ``fused``, else numpy."""
    if fused and _velocity_kernel is not None:
        out = np.empty((len(rest), 3))
        _velocity_kernel(np.ascontiguousarray(rest, np.float64), np.ascontiguousarray(moving, np.float64), *field,
                         np.asarray(centre, np.float64), float(radius),
                         np.zeros((0,) + (BLOCK_CELLS + 1,) * 3 + (3,)) if moving_offsets is None else
                         np.ascontiguousarray(moving_offsets, np.float64), out)
        return out
    homogeneous = np.concatenate([rest, np.ones((len(rest), 1))], axis=1)
    velocity = np.einsum("nab,nb->na", blend_at(rest, moving, field, centre, radius), homogeneous)
    if moving_offsets is not None:
        velocity += offsets_at(rest, moving_offsets, field, centre, radius)[0]
    return velocity


def parts_through_skinning(points: np.ndarray, to_rest: np.ndarray, posed: np.ndarray, labels: np.ndarray,
                           centre, radius: float, allowed: np.ndarray, part_boxes: np.ndarray, field,
                           iterations: int, solver: str, rule: str = "own-label", fused: bool = True,
                           offsets: np.ndarray | None = None):
    """Each point's candidate parts and their rest points, the rows :func:`carry_to_rest` would
    keep (:func:`candidate_rows_through_skinning`: the rule's two groups joined, the unusable rows
    dropped): ``(point (k,) int64, joint (k,) int64, rest (k, 3), inverse (k, 3, 3))`` float64,
    sorted by joint, every point with at least one row."""
    point, joint, carried = candidate_rows_through_skinning(points, to_rest, posed, labels, centre, radius, allowed,
                                                            part_boxes, field, iterations, solver, rule, fused,
                                                            offsets=offsets)
    if carried.usable.all():  # nothing dropped: no copies of the rows
        return point, joint, carried.rest, carried.inverse
    keep = np.flatnonzero(carried.usable)
    return point[keep], joint[keep], carried.rest[keep], carried.inverse[keep]


class CandidateRows(NamedTuple):
    """A group of candidate rows (:func:`candidate_groups_through_skinning`): ``point`` (m,) int64
    (indices into the query's points), ``joint`` (m,) int64 and ``rows`` (:class:`CarriedRows`)."""

    point: np.ndarray
    joint: np.ndarray
    rows: CarriedRows


def candidate_groups_through_skinning(points: np.ndarray, to_rest: np.ndarray, posed: np.ndarray,
                                      labels: np.ndarray, centre, radius: float, allowed: np.ndarray,
                                      part_boxes: np.ndarray, field, iterations: int, solver: str,
                                      rule: str = "own-label", fused: bool = True, moving: np.ndarray | None = None,
                                      rest_boxes: np.ndarray | None = None, offsets: np.ndarray | None = None,
                                      moving_offsets: np.ndarray | None = None, table: np.ndarray | None = None
                                      ) -> tuple[CandidateRows, CandidateRows | None]:
    """The candidate rule (``rule``, :data:`CANDIDATE_RULES`) in its one home, for the query and
    the training alike: :func:`part_candidates` (the label at each part's rigid image), carried on
    through the skinning by :func:`carried_rows`; with ``retry-labels``, a point none of whose
    candidates reached a root is tried again with the parts :func:`labels_seen` names at its
    rigid images (those not tried yet): where one of them reaches a root, those rows replace the
    first ones (else the first ones stay). ``points`` (n, 3) float64, collider frame at the pose;
    ``to_rest`` (J, 3, 4) and ``posed`` (J, 4, 4) (:func:`rest_maps`); ``moving``, ``offsets``,
    ``moving_offsets`` and ``table`` as :func:`carried_rows`'; the rest (``rest_boxes`` too) as
    :func:`part_candidates` and :func:`carry_to_rest`.

    Returns ``(first, retried)`` (:class:`CandidateRows`), the rows as they were carried, not
    joined (the query's: no copies of a million rows for the few retried ones): the first rows
    (sorted by joint, then point) and the retried ones (the same order; None where none were
    tried), ``usable`` telling in each which rows count. A point's usable rows are all in one
    group: where a retried row reached a root, none of the point's first rows is usable
    (:func:`candidate_rows_through_skinning` joins the two)."""
    if rule not in CANDIDATE_RULES:
        raise ValueError(f"candidate rule must be one of {', '.join(CANDIDATE_RULES)}, got {rule!r}")
    point, joint, rigid = part_candidates(points, to_rest, labels, centre, radius, allowed, part_boxes, fused,
                                          rest_boxes)
    carried = carried_rows(points, point, joint, rigid, to_rest, posed, field, centre, radius, iterations, solver,
                           fused, moving, offsets, moving_offsets, table)
    if rule != "retry-labels" or carried.converged.all():
        return CandidateRows(point, joint, carried), None
    reached = np.zeros(len(points), bool)
    reached[point[carried.converged]] = True
    lost = np.unique(point[~reached[point]])  # points with rows, none of which reached a root
    seen = labels_seen(points[lost], to_rest, labels, centre, radius, fused)
    where = np.full(len(points), -1, np.int64)
    where[lost] = np.arange(len(lost))
    tried = where[point] >= 0
    seen[joint[tried], where[point[tried]]] = False  # tried already
    retry_joint, column = np.nonzero(seen)
    if not len(column):
        return CandidateRows(point, joint, carried), None
    retry_point = lost[column]
    retry_rigid = (np.einsum("mab,mb->ma", to_rest[retry_joint, :, :3], points[retry_point])
                   + to_rest[retry_joint, :, 3])
    again = carried_rows(points, retry_point, retry_joint, retry_rigid, to_rest, posed, field, centre, radius,
                         iterations, solver, fused, moving, offsets, moving_offsets, table)
    found = np.zeros(len(points), bool)
    found[retry_point[again.converged]] = True  # a root reached: these rows replace the first ones
    lost_rows = np.flatnonzero(found[point])
    first_usable = carried.usable.copy() if len(lost_rows) else carried.usable
    first_usable[lost_rows] = False
    return (CandidateRows(point, joint, carried._replace(usable=first_usable)),
            CandidateRows(retry_point, retry_joint, again._replace(usable=again.usable & found[retry_point])))


def candidate_rows_through_skinning(points: np.ndarray, to_rest: np.ndarray, posed: np.ndarray, labels: np.ndarray,
                                    centre, radius: float, allowed: np.ndarray, part_boxes: np.ndarray, field,
                                    iterations: int, solver: str, rule: str = "own-label", fused: bool = True,
                                    moving: np.ndarray | None = None, rest_boxes: np.ndarray | None = None,
                                    offsets: np.ndarray | None = None, moving_offsets: np.ndarray | None = None
                                    ) -> tuple[np.ndarray, np.ndarray, CarriedRows]:
    """:func:`candidate_groups_through_skinning`'s two groups joined into one: the first rows of
    the points whose retried rows reached no root, then those retried rows, in one order.

    Returns ``(point (m,) int64, joint (m,) int64, rows)``: every row (:class:`CarriedRows`; the
    union reads only the ``usable`` ones), sorted by joint (within a joint by point, the retried
    rows after the first ones), one row per point and joint, every point with a usable row."""
    first, retried = candidate_groups_through_skinning(points, to_rest, posed, labels, centre, radius, allowed,
                                                       part_boxes, field, iterations, solver, rule, fused, moving,
                                                       rest_boxes, offsets, moving_offsets)
    if retried is None:
        return first
    found = np.zeros(len(points), bool)
    found[retried.point[retried.rows.usable]] = True
    keep_first, keep_second = ~found[first.point], found[retried.point]
    joint = np.concatenate([first.joint[keep_first], retried.joint[keep_second]])
    order = np.argsort(joint.astype(np.int16), kind="stable")  # a radix sort: parts are < 255
    # Each joined row's source in the first rows followed by the retried ones: one gather per array.
    source = np.concatenate([np.flatnonzero(keep_first), len(keep_first) + np.flatnonzero(keep_second)])[order]

    def joined(a, b):
        return joined_rows(a, b, source, fused)

    carried, again = first.rows, retried.rows
    usable = joined(carried.usable, again.usable)
    velocity = None if carried.velocity is None or again.velocity is None else joined(carried.velocity,
                                                                                      again.velocity)
    rows = CarriedRows(usable, joined(carried.rest, again.rest), joined(carried.inverse, again.inverse), velocity,
                       joined(carried.converged, again.converged))
    return joined(first.point, retried.point), joint[order], rows


def joined_rows(a: np.ndarray, b: np.ndarray, source: np.ndarray, fused: bool = True) -> np.ndarray:
    """Rows ``source`` (k,) int64 of ``a`` (m, ...) followed by ``b`` (m', ...) (same dtype and row
    shape): ``concatenate([a, b])[source]``, in one parallel numba gather (:func:`_join_kernel`,
    no concatenated copy) when numba is there and ``fused``, else numpy."""
    if fused and _join_kernel is not None:
        out = np.empty((len(source),) + a.shape[1:], a.dtype)
        _join_kernel(np.ascontiguousarray(a).reshape(len(a), -1), np.ascontiguousarray(b).reshape(len(b), -1),
                     np.ascontiguousarray(source, np.int64), out.reshape(len(source), -1))
        return out
    return np.concatenate([a, b])[source]


_join_kernel = None
if grid_kernels.available():
    import numba

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _join_kernel(a, b, source, out):  # pragma: no cover
        """:func:`joined_rows` over the rows (numba): ``out`` (k, w) overwritten from ``a`` (m, w)
        and ``b`` (m', w)."""
        m = a.shape[0]
        for r in numba.prange(source.shape[0]):
            s = source[r]
            if s < m:
                out[r, :] = a[s, :]
            else:
                out[r, :] = b[s - m, :]


#: Rows per task of the Newton pass (each task allocates its scratch once).
NEWTON_CHUNK = 1024
#: From this many rows on, the Newton pass reads the fine blocks through the pose's table
#: (:func:`pose_table`; a collider keeps the last pose's, else each pass builds one: 1.4-3 ms on the
#: walker's 904 blocks, 2 threads, up to 30 ms in fresh memory; it saves about 0.1 us a row, so it
#: pays back at about 20,000 rows).
NEWTON_TABLE_ROWS = 32768


def spread_stride(chunks: int) -> int:
    """A stride coprime with ``chunks`` near 0.618 of it: task i of a parallel pass takes chunk ``(i *
    stride) % chunks``, so that the contiguous share of tasks each thread gets (numba's static
    schedule) is spread over all the rows. Rows come sorted by joint, and one part's rows can cost
    3x another's (measured on the walker: the first half of a chunk's rows 0.49 s, the second
    0.14 s on one thread): in contiguous halves one core idled."""
    stride = max(1, int(round(0.6180339887 * chunks)))
    while math.gcd(stride, chunks) != 1:
        stride -= 1
    return stride


def _newton_through_grid(points, point, rigid, posed, field, centre, radius: float, iterations: int,
                         fused: bool = True, moving: np.ndarray | None = None, offsets: np.ndarray | None = None,
                         moving_offsets: np.ndarray | None = None, table: np.ndarray | None = None):
    """:func:`newton_rest` of rows ``point`` (m,) int64 of ``points`` (n, 3) from ``rigid`` (m, 3)
    through the weight grid (:func:`weights_and_gradient`), its tolerance
    :data:`NEWTON_TOLERANCE` and longest step :data:`NEWTON_MAX_STEP` times ``radius``: one numba
    pass (:func:`_newton_kernel`, which reads the points through ``point``: no gathered copy) when
    numba is there and ``fused``, else numpy. Returns ``newton_rest``'s three, the velocity (m, 3)
    at the rest points (:func:`_velocity_at`) from the kernel's last weights where ``moving`` (J,
    3, 4) is given and the kernel ran (else None), and the rows (k,) int64 that moved further than
    :data:`DIVERGED` times ``radius`` from ``rigid``. ``offsets``, ``moving_offsets`` and ``table``
    as :func:`carried_rows`'."""
    centre = np.asarray(centre, np.float64)
    tolerance, max_step, last_step = NEWTON_TOLERANCE * radius, NEWTON_MAX_STEP * radius, NEWTON_LAST_STEP * radius
    limit = (DIVERGED * radius) ** 2
    rigid = np.ascontiguousarray(rigid, np.float64)
    if fused and _newton_kernel is not None:
        rest = np.empty_like(rigid)
        inverse = np.empty((len(rest), 3, 3))
        converged = np.empty(len(rest), np.bool_)
        wild = np.empty(len(rest), np.bool_)
        if moving is None:
            maps, velocity = np.zeros((0, 3, 4)), np.empty((0, 3))
        else:
            maps, velocity = np.ascontiguousarray(moving, np.float64), np.empty((len(rest), 3))
        none = np.zeros((0,) + (BLOCK_CELLS + 1,) * 3 + (3,))
        if table is None and uses_table(len(rest), field):
            table = pose_table(field, posed, moving, offsets, moving_offsets)
        if table is None:
            table = np.zeros((0,) + (BLOCK_CELLS + 1,) * 3 + (BLENDED_CHANNELS,))
        elif table.shape[-1] != BLENDED_CHANNELS * (1 if moving is None else 2):
            raise ValueError(f"a pose table of {table.shape[-1]} channels for a pass "
                             f"{'without' if moving is None else 'with'} the motion")
        _newton_kernel(np.ascontiguousarray(points, np.float64), np.ascontiguousarray(point, np.int64), rigid, rest,
                       np.ascontiguousarray(posed[:, :3, :]), *field, centre, float(radius), iterations, max_step,
                       tolerance, last_step, NEWTON_HALVINGS, limit, inverse, converged, wild, maps, velocity,
                       spread_stride((len(rest) + NEWTON_CHUNK - 1) // NEWTON_CHUNK),
                       none if offsets is None else np.ascontiguousarray(offsets, np.float64),
                       none if moving is None or moving_offsets is None else
                       np.ascontiguousarray(moving_offsets, np.float64), table)
        return rest, inverse, converged, (None if moving is None else velocity), np.flatnonzero(wild)
    joints = len(posed)

    def weights(y):
        return weights_and_gradient(y, field, centre, radius, joints)

    offset = None if offsets is None else (lambda y: offsets_at(y, offsets, field, centre, radius))
    rest, inverse, converged = newton_rest(points[point], rigid, posed, weights, iterations, max_step, tolerance,
                                           last_step, lambda y: weight_cells(y, field, centre, radius), offset)
    moved = rest - rigid
    return rest, inverse, converged, None, np.flatnonzero(np.einsum("ma,ma->m", moved, moved) > limit)


_blend_kernel = _skinned_rest_kernel = _offsets_kernel = _blend_table_kernel = _velocity_kernel = None
if grid_kernels.available():
    import numba

    @numba.njit(cache=True, nogil=True)
    def _weight_cell(value, centre, radius, side):  # pragma: no cover
        """Corner index below and the fraction along one axis of the weight grid (clamped)."""
        u = min(max((value - centre) / radius, -1.0), 1.0)
        position = (u + 1.0) * 0.5 * (side - 1)
        c = min(int(math.floor(position)), side - 2)
        return c, position - c

    @numba.njit(cache=True, nogil=True)
    def _weight_axis(value, centre, radius, cells):  # pragma: no cover
        """Corner index below, fraction and d(fraction)/d(value) (0 where clamped) along one axis
        of a weight grid of ``cells`` cells per side."""
        c, t = _weight_cell(value, centre, radius, cells + 1)
        u = (value - centre) / radius
        return c, t, (0.0 if (u < -1.0 or u > 1.0) else 0.5 * cells / radius)

    # The helpers that take arrays and run per row of the weight passes are inlined: a call that
    # passes arrays pays their reference counts, which the pass's threads contend for (inlined,
    # on the walker the Newton pass took 0.76x the time, the fixed-point steps 0.53x, the same
    # bits; numba compiles them in ~9 s more, once).
    @numba.njit(cache=True, nogil=True, inline="always")
    def _fine_cell(x, y, z, block_index, centre, radius):  # pragma: no cover
        """Where the rest point (x, y, z) lies in the fine blocks: ``(row, cx, cy, cz, tx, ty, tz, sx,
        sy, sz)``, the block's row (-1: no stored block there, or no fine field) and per axis the
        corner index below in the block, the fraction and its derivative."""
        blocks = block_index.shape[0]
        if blocks == 0:
            return -1, 0, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        cells = blocks * BLOCK_CELLS
        cx, tx, sx = _weight_axis(x, centre[0], radius, cells)
        cy, ty, sy = _weight_axis(y, centre[1], radius, cells)
        cz, tz, sz = _weight_axis(z, centre[2], radius, cells)
        bx, by, bz = cx // BLOCK_CELLS, cy // BLOCK_CELLS, cz // BLOCK_CELLS
        return (block_index[bx, by, bz], cx - bx * BLOCK_CELLS, cy - by * BLOCK_CELLS, cz - bz * BLOCK_CELLS, tx, ty,
                tz, sx, sy, sz)

    @numba.njit(cache=True, nogil=True, inline="always")
    def _weight_source(x, y, z, grid_joints, grid_weights, block_index, block_joints, block_weights, centre,
                       radius):  # pragma: no cover
        """Where the rest point (x, y, z) reads the :class:`WeightField`: ``(joints, weights)`` (the
        fine block's corners, or the coarse grid's), per axis the corner index below in them, the
        fraction and its derivative, and the block's row (-1: the coarse grid). :func:`_corner_tables`
        in numba."""
        row, cx, cy, cz, tx, ty, tz, sx, sy, sz = _fine_cell(x, y, z, block_index, centre, radius)
        if row >= 0:
            return block_joints[row], block_weights[row], cx, cy, cz, tx, ty, tz, sx, sy, sz, row
        cells = grid_joints.shape[0] - 1
        cx, tx, sx = _weight_axis(x, centre[0], radius, cells)
        cy, ty, sy = _weight_axis(y, centre[1], radius, cells)
        cz, tz, sz = _weight_axis(z, centre[2], radius, cells)
        return grid_joints, grid_weights, cx, cy, cz, tx, ty, tz, sx, sy, sz, -1

    @numba.njit(cache=True, nogil=True, inline="always")
    def _corner_weight(corner, tx, ty, tz, sx, sy, sz):  # pragma: no cover
        """Corner ``corner``'s offsets (ox, oy, oz) in its cell (bit a along axis a), its trilinear
        weight at fractions (tx, ty, tz) and that weight's derivative along x, y, z (``sx``, ``sy``,
        ``sz``: d fraction / d position)."""
        ox, oy, oz = corner & 1, (corner >> 1) & 1, (corner >> 2) & 1
        fx = tx if ox else 1.0 - tx
        fy = ty if oy else 1.0 - ty
        fz = tz if oz else 1.0 - tz
        gx = sx if ox else -sx
        gy = sy if oy else -sy
        gz = sz if oz else -sz
        return ox, oy, oz, fx * fy * fz, gx * fy * fz, fx * gy * fz, fx * fy * gz

    @numba.njit(cache=True, nogil=True, inline="always")
    def _gather_weights(table_joints, table_weights, cx, cy, cz, tx, ty, tz, sx, sy, sz, slot_of, touched, wsum,
                        dsum):  # pragma: no cover
        """The 8 corners' weights summed per joint: ``touched[:count]`` the joints, ``wsum[:count]``
        their interpolated raw weights and ``dsum[:count]`` (count, 3) those weights' derivatives
        along x, y, z (per collider unit); returns count. ``slot_of`` (J,) int64 all -1 (left so).
        Summing per joint first leaves each joint's map to be read once, not once per corner."""
        count = 0
        for corner in range(8):
            ox, oy, oz, tw, d0, d1, d2 = _corner_weight(corner, tx, ty, tz, sx, sy, sz)
            i, j, k = cx + ox, cy + oy, cz + oz
            for slot in range(table_joints.shape[3]):
                raw = table_weights[i, j, k, slot]
                if raw == 0:  # (before the division: most corners hold 1-2 joints)
                    continue
                q = raw / 255.0
                joint = table_joints[i, j, k, slot]
                s = slot_of[joint]
                if s < 0:
                    s = count
                    slot_of[joint] = s
                    touched[s] = joint
                    wsum[s] = 0.0
                    dsum[s, 0] = dsum[s, 1] = dsum[s, 2] = 0.0
                    count += 1
                wsum[s] += tw * q
                dsum[s, 0] += d0 * q
                dsum[s, 1] += d1 * q
                dsum[s, 2] += d2 * q
        for s in range(count):
            slot_of[touched[s]] = -1
        return count

    @numba.njit(cache=True, nogil=True, inline="always")
    def _gather_scratch(joints):  # pragma: no cover
        """:func:`_gather_weights`' scratch for one task of a pass: ``slot_of`` (J,) all -1,
        ``touched``, ``wsum`` and ``dsum``."""
        return (np.full(joints, -1, np.int64), np.empty(8 * GRID_INFLUENCES, np.int64), np.empty(8 * GRID_INFLUENCES),
                np.empty((8 * GRID_INFLUENCES, 3)))

    @numba.njit(cache=True, nogil=True, inline="always")
    def _blend_one(x, y, z, maps, grid_joints, grid_weights, block_index, block_joints, block_weights, centre,
                   radius, out, p, slot_of, touched, wsum, dsum):  # pragma: no cover
        """``out[p]`` (3, 4) = the weight-blended ``maps`` at the rest point (x, y, z); the last four:
        :func:`_gather_weights`' scratch."""
        table_joints, table_weights, cx, cy, cz, tx, ty, tz, sx, sy, sz, _ = _weight_source(
            x, y, z, grid_joints, grid_weights, block_index, block_joints, block_weights, centre, radius)
        count = _gather_weights(table_joints, table_weights, cx, cy, cz, tx, ty, tz, sx, sy, sz, slot_of, touched,
                                wsum, dsum)
        total = 0.0
        for s in range(count):
            total += wsum[s]
        scale = 1.0 / max(total, 1e-12)
        for a in range(3):
            for b in range(4):
                value = 0.0
                for s in range(count):
                    value += wsum[s] * maps[touched[s], a, b]
                out[p, a, b] = value * scale

    #: Points per task of the weight passes (each task allocates its scratch once).
    WEIGHT_CHUNK = 1024

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _blend_kernel(rest, maps, grid_joints, grid_weights, block_index, block_joints, block_weights, centre, radius,
                      out):  # pragma: no cover
        """:func:`blend_at` in one pass over the points (numba): ``out`` (m, 3, 4) overwritten."""
        n = rest.shape[0]
        for first in numba.prange((n + WEIGHT_CHUNK - 1) // WEIGHT_CHUNK):
            slot_of, touched, wsum, dsum = _gather_scratch(maps.shape[0])
            for p in range(first * WEIGHT_CHUNK, min(n, first * WEIGHT_CHUNK + WEIGHT_CHUNK)):
                _blend_one(rest[p, 0], rest[p, 1], rest[p, 2], maps, grid_joints, grid_weights, block_index,
                           block_joints, block_weights, centre, radius, out, p, slot_of, touched, wsum, dsum)

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _velocity_kernel(rest, moving, grid_joints, grid_weights, block_index, block_joints, block_weights, centre,
                         radius, moving_offsets, out):  # pragma: no cover
        """:func:`_velocity_at` in one pass over the points (numba): ``out`` (m, 3) overwritten;
        ``moving_offsets`` (k, 5, 5, 5, 3), or with no rows none."""
        n = rest.shape[0]
        for first in numba.prange((n + WEIGHT_CHUNK - 1) // WEIGHT_CHUNK):
            slot_of, touched, wsum, dsum = _gather_scratch(moving.shape[0])
            blend = np.empty((1, 3, 4))
            for p in range(first * WEIGHT_CHUNK, min(n, first * WEIGHT_CHUNK + WEIGHT_CHUNK)):
                x, y, z = rest[p, 0], rest[p, 1], rest[p, 2]
                _blend_one(x, y, z, moving, grid_joints, grid_weights, block_index, block_joints, block_weights,
                           centre, radius, blend, 0, slot_of, touched, wsum, dsum)
                for a in range(3):
                    out[p, a] = blend[0, a, 0] * x + blend[0, a, 1] * y + blend[0, a, 2] * z + blend[0, a, 3]
                if moving_offsets.shape[0]:
                    row, cx, cy, cz, tx, ty, tz, _, _, _ = _fine_cell(x, y, z, block_index, centre, radius)
                    if row >= 0:
                        _add_blended_offset(out[p], moving_offsets, row, cx, cy, cz, tx, ty, tz)

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _blend_table_kernel(joints, weights, maps, offsets, out):  # pragma: no cover
        """:func:`blended_blocks` over the corners (numba): ``joints``, ``weights`` (c, 4) uint8,
        ``maps`` (S, J, 3, 4), ``offsets`` (S, c, 3); ``out`` (c, 16 S) overwritten."""
        for c in numba.prange(joints.shape[0]):
            for m in range(maps.shape[0]):
                first = m * BLENDED_CHANNELS
                for i in range(12):
                    out[c, first + i] = 0.0
                total = 0.0
                for slot in range(joints.shape[1]):
                    raw = weights[c, slot]
                    if raw == 0:
                        continue
                    q = raw / 255.0
                    j = joints[c, slot]
                    total += q
                    for a in range(3):
                        for b in range(4):
                            out[c, first + 4 * a + b] += q * maps[m, j, a, b]
                out[c, first + 12] = total
                for a in range(3):
                    out[c, first + 13 + a] = offsets[m, c, a]

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _skinned_rest_kernel(points, rest, maps, grid_joints, grid_weights, block_index, block_joints, block_weights,
                             centre, radius, iterations, blend, inverse):  # pragma: no cover
        """:func:`skinned_rest` in one pass over the points (numba): ``rest`` (m, 3) is moved in
        place, ``inverse`` (m, 3, 3) overwritten; ``blend`` (m, 3, 4) scratch."""
        n = points.shape[0]
        for first in numba.prange((n + WEIGHT_CHUNK - 1) // WEIGHT_CHUNK):
            slot_of, touched, wsum, dsum = _gather_scratch(maps.shape[0])
            for p in range(first * WEIGHT_CHUNK, min(n, first * WEIGHT_CHUNK + WEIGHT_CHUNK)):
                for _ in range(iterations):
                    _blend_one(rest[p, 0], rest[p, 1], rest[p, 2], maps, grid_joints, grid_weights, block_index,
                               block_joints, block_weights, centre, radius, blend, p, slot_of, touched, wsum, dsum)
                    m = blend[p]
                    _inverse3(m, inverse[p])
                    inv = inverse[p]
                    dx, dy, dz = points[p, 0] - m[0, 3], points[p, 1] - m[1, 3], points[p, 2] - m[2, 3]
                    for a in range(3):
                        rest[p, a] = inv[a, 0] * dx + inv[a, 1] * dy + inv[a, 2] * dz

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _offsets_kernel(vertices, vertex_joints, vertex_weights, triangle, bary, joints, weights, maps,
                        out):  # pragma: no cover
        """:func:`surface_offsets` (numba), for each map set ``maps`` (M, J, 3, 4): the skin's rest
        ``vertices`` (V, 3) with their joints and weights (V, I), per corner its anchor's
        ``triangle`` (n, 3) and ``bary`` (n, 3) and its ``joints``, ``weights`` (n, 4) uint8;
        ``out`` (M, n, 3) overwritten. The skin's vertices under the maps first, then the corners."""
        sets = maps.shape[0]
        moved = np.zeros((sets, vertices.shape[0], 3))
        for v in numba.prange(vertices.shape[0]):
            for k in range(vertex_joints.shape[1]):
                w = vertex_weights[v, k]
                if w == 0.0:
                    continue
                j = vertex_joints[v, k]
                for m in range(sets):
                    for a in range(3):
                        moved[m, v, a] += w * (maps[m, j, a, 0] * vertices[v, 0] + maps[m, j, a, 1] * vertices[v, 1]
                                               + maps[m, j, a, 2] * vertices[v, 2] + maps[m, j, a, 3])
        for c in numba.prange(triangle.shape[0]):
            p0 = p1 = p2 = 0.0
            for i in range(3):
                p0 += bary[c, i] * vertices[triangle[c, i], 0]
                p1 += bary[c, i] * vertices[triangle[c, i], 1]
                p2 += bary[c, i] * vertices[triangle[c, i], 2]
            total = 0.0
            for slot in range(joints.shape[1]):
                total += weights[c, slot] / 255.0
            scale = 1.0 / max(total, 1e-12)
            for m in range(sets):
                for a in range(3):
                    flat = 0.0  # the face's skinned vertices, blended
                    for i in range(3):
                        flat += bary[c, i] * moved[m, triangle[c, i], a]
                    skinned = 0.0  # the anchor skinned by the corner's weights
                    for slot in range(joints.shape[1]):
                        raw = weights[c, slot]
                        if raw != 0:
                            j = joints[c, slot]
                            skinned += raw / 255.0 * (maps[m, j, a, 0] * p0 + maps[m, j, a, 1] * p1
                                                      + maps[m, j, a, 2] * p2 + maps[m, j, a, 3])
                    out[m, c, a] = flat - skinned * scale

    @numba.njit(cache=True, nogil=True, inline="always")
    def _inverse3(m, out):  # pragma: no cover
        """``out`` (3, 3) = the inverse of ``m`` (3, 3) (cofactors; a singular m as if det 1e-300)."""
        c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
        c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
        c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
        det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
        det = det if det != 0.0 else 1e-300
        out[0, 0], out[1, 0], out[2, 0] = c00 / det, c01 / det, c02 / det
        out[0, 1] = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) / det
        out[1, 1] = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) / det
        out[2, 1] = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) / det
        out[0, 2] = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) / det
        out[1, 2] = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) / det
        out[2, 2] = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) / det


_newton_kernel = None
if grid_kernels.available():
    import numba

    @numba.njit(cache=True, nogil=True, inline="always")
    def _add_map_row(row, maps, j, a, w, g0, g1, g2, y0, y1, y2):  # pragma: no cover
        """``row`` (7 floats: row a of sum_k w_k A_k, then of sum_k (A_k [y, 1])_a grad w_k) plus
        joint j's share, weight ``w`` and weight derivative (g0, g1, g2) at the rest point y."""
        m0, m1, m2, m3 = maps[j, a, 0], maps[j, a, 1], maps[j, a, 2], maps[j, a, 3]
        moved = m0 * y0 + m1 * y1 + m2 * y2 + m3
        return (row[0] + w * m0, row[1] + w * m1, row[2] + w * m2, row[3] + w * m3, row[4] + moved * g0,
                row[5] + moved * g1, row[6] + moved * g2)

    @numba.njit(cache=True, nogil=True, inline="always")
    def _add_blended_offset(out, offsets, block, cx, cy, cz, tx, ty, tz):  # pragma: no cover
        """``out`` (3,) += ``offsets`` (k, 5, 5, 5, 3) of block ``block``'s corners blended
        trilinearly in the cell (cx, cy, cz) at fractions (tx, ty, tz) (a velocity's offsets)."""
        for corner in range(8):
            ox, oy, oz, tw, _, _, _ = _corner_weight(corner, tx, ty, tz, 0.0, 0.0, 0.0)
            for a in range(3):
                out[a] += tw * offsets[block, cx + ox, cy + oy, cz + oz, a]

    @numba.njit(cache=True, nogil=True, inline="always")
    def _table_blend(table, block, cx, cy, cz, tx, ty, tz, sx, sy, sz, blend, first,
                     derivatives):  # pragma: no cover
        """``blend[0]`` (16,) = channels ``first`` .. ``first + 15`` (one map set) of block
        ``block``'s corners of ``table`` (:func:`blended_blocks`) blended trilinearly in the cell
        (cx, cy, cz) at fractions (tx, ty, tz), and with ``derivatives`` ``blend[1:4]`` their
        derivatives along x, y, z (``sx``, ``sy``, ``sz``: d fraction / d rest). The channels
        innermost and contiguous: the compiler takes them four at a time (an evaluation of the
        Newton terms 1.4x as fast as the sums per joint on the walker, docs/neural.md)."""
        blend[:, :] = 0.0
        for corner in range(8):
            ox, oy, oz, tw, e0, e1, e2 = _corner_weight(corner, tx, ty, tz, sx, sy, sz)
            if derivatives:
                for i in range(BLENDED_CHANNELS):
                    value = table[block, cx + ox, cy + oy, cz + oz, first + i]
                    blend[0, i] += tw * value
                    blend[1, i] += e0 * value
                    blend[2, i] += e1 * value
                    blend[3, i] += e2 * value
            else:
                for i in range(BLENDED_CHANNELS):
                    blend[0, i] += tw * table[block, cx + ox, cy + oy, cz + oz, first + i]

    @numba.njit(cache=True, nogil=True, inline="always")
    def _table_terms(table, block, cx, cy, cz, tx, ty, tz, sx, sy, sz, y0, y1, y2, x, f, jac,
                     blend):  # pragma: no cover
        """:func:`_newton_terms_one`'s ``f``, ``jac`` and |F| from a :func:`blended_blocks` table (the
        same sums, regrouped by corner: ``M(y) = sum_c t_c M_c``, ``dM/dy_b = sum_c dt_c/dy_b M_c``)."""
        _table_blend(table, block, cx, cy, cz, tx, ty, tz, sx, sy, sz, blend, 0, True)
        total = max(blend[0, 12], 1e-12)
        size = 0.0
        for a in range(3):
            image = (blend[0, 4 * a] * y0 + blend[0, 4 * a + 1] * y1 + blend[0, 4 * a + 2] * y2
                     + blend[0, 4 * a + 3]) / total
            f[a] = image - x[a] + blend[0, 13 + a]
            for b in range(3):
                moved = (blend[1 + b, 4 * a] * y0 + blend[1 + b, 4 * a + 1] * y1 + blend[1 + b, 4 * a + 2] * y2
                         + blend[1 + b, 4 * a + 3])
                jac[a, b] = (blend[0, 4 * a + b] + moved - image * blend[1 + b, 12]) / total + blend[1 + b, 13 + a]
            size += f[a] * f[a]
        return math.sqrt(size)

    @numba.njit(cache=True, nogil=True, inline="always")
    def _newton_terms_one(y0, y1, y2, x, maps, field, centre, radius, f, jac, slot_of, touched, wsum, dsum,
                          offsets, table, blend):  # pragma: no cover
        """``f`` (3,) = F and ``jac`` (3, 3) = J_F of :func:`newton_rest` at the rest point (y0, y1,
        y2) for the posed point ``x`` (3,), the blended ``offsets`` added where it has rows
        (:func:`surface_offsets`; in the fine blocks); returns ``(|F|, count, block row, cx, cy, cz,
        tx, ty, tz)``: the cell, for the velocity's offsets. The four before ``offsets``:
        :func:`_gather_weights`' scratch (``touched[:count]``, ``wsum[:count]``: the point's joints
        and raw weights, as left there). In a fine block, where ``table`` (:func:`blended_blocks`
        of the maps and offsets) has rows, the terms are its (:func:`_table_terms`; count 0),
        ``blend`` (4, 16) its scratch."""
        if table.shape[0]:
            block, cx, cy, cz, tx, ty, tz, sx, sy, sz = _fine_cell(y0, y1, y2, field[2], centre, radius)
            if block >= 0:
                size = _table_terms(table, block, cx, cy, cz, tx, ty, tz, sx, sy, sz, y0, y1, y2, x, f, jac, blend)
                return size, 0, block, cx, cy, cz, tx, ty, tz
        table_joints, table_weights, cx, cy, cz, tx, ty, tz, sx, sy, sz, block = _weight_source(
            y0, y1, y2, field[0], field[1], field[2], field[3], field[4], centre, radius)
        count = _gather_weights(table_joints, table_weights, cx, cy, cz, tx, ty, tz, sx, sy, sz, slot_of, touched,
                                wsum, dsum)
        # One pass over the joints, each map row read once, into tuples of scalars (each sum over the
        # joints in order, as with a pass per row: the same bits; the evaluation a tenth faster).
        total = ds0 = ds1 = ds2 = 0.0
        row0 = row1 = row2 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        for s in range(count):
            w = wsum[s]
            g0, g1, g2 = dsum[s, 0], dsum[s, 1], dsum[s, 2]
            total += w
            ds0 += g0
            ds1 += g1
            ds2 += g2
            j = touched[s]
            row0 = _add_map_row(row0, maps, j, 0, w, g0, g1, g2, y0, y1, y2)
            row1 = _add_map_row(row1, maps, j, 1, w, g0, g1, g2, y0, y1, y2)
            row2 = _add_map_row(row2, maps, j, 2, w, g0, g1, g2, y0, y1, y2)
        total = max(total, 1e-12)
        size = 0.0
        for a, row in enumerate((row0, row1, row2)):
            image = (row[0] * y0 + row[1] * y1 + row[2] * y2 + row[3]) / total
            f[a] = image - x[a]
            jac[a, 0] = (row[0] + row[4] - image * ds0) / total
            jac[a, 1] = (row[1] + row[5] - image * ds1) / total
            jac[a, 2] = (row[2] + row[6] - image * ds2) / total
        if block >= 0 and offsets.shape[0]:
            _add_offsets(offsets, block, cx, cy, cz, tx, ty, tz, sx, sy, sz, f, jac)
        for a in range(3):
            size += f[a] * f[a]
        return math.sqrt(size), count, block, cx, cy, cz, tx, ty, tz

    @numba.njit(cache=True, nogil=True, inline="always")
    def _add_offsets(offsets, block, cx, cy, cz, tx, ty, tz, sx, sy, sz, f, jac):  # pragma: no cover
        """``f`` (3,) and ``jac`` (3, 3) plus the trilinear blend of block ``block``'s corner
        ``offsets`` (:func:`surface_offsets`) in the cell (cx, cy, cz) at fractions (tx, ty, tz),
        and its derivative (d fraction / d rest: sx, sy, sz). :func:`offsets_at` in numba."""
        for corner in range(8):
            ox, oy, oz, tw, e0, e1, e2 = _corner_weight(corner, tx, ty, tz, sx, sy, sz)
            for a in range(3):
                value = offsets[block, cx + ox, cy + oy, cz + oz, a]
                f[a] += tw * value
                jac[a, 0] += value * e0
                jac[a, 1] += value * e1
                jac[a, 2] += value * e2

    @numba.njit(cache=True, nogil=True, inline="always")
    def _same_weight_cell(a0, a1, a2, b0, b1, b2, field, centre, radius):  # pragma: no cover
        """Whether rest points a and b lie in the same cells of the weight grid and of its fine
        grid (:func:`weight_cells` in numba)."""
        for cells in (field[0].shape[0] - 1, field[2].shape[0] * BLOCK_CELLS):
            if cells == 0:
                continue
            for a, b, c in ((a0, b0, centre[0]), (a1, b1, centre[1]), (a2, b2, centre[2])):
                if _weight_cell(a, c, radius, cells + 1)[0] != _weight_cell(b, c, radius, cells + 1)[0]:
                    return False
        return True

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _newton_kernel(points, point, start, rest, maps, grid_joints, grid_weights, block_index, block_joints,
                       block_weights, centre, radius, iterations, max_step, tolerance, last_step, halvings, limit,
                       inverse, converged, wild, moving, velocity, stride, offsets, moving_offsets,
                       table):  # pragma: no cover
        """:func:`newton_rest` through the weight grid in one pass over the rows (numba): row r the
        posed point ``points[point[r]]`` from ``start`` (m, 3); ``rest`` (m, 3), ``inverse`` (m, 3,
        3) and ``converged`` (m,) overwritten, and ``wild`` (m,): whether the rest point lies further
        than ``sqrt(limit)`` from its start (the three squares summed in order, as numpy sums them).
        Where ``moving`` (J, 3, 4) has rows (else (0, 3, 4)), ``velocity`` (m, 3) is overwritten
        with :func:`blend_at`'s ``sum_k w_k dA_k/dt`` applied to the final rest point, with the
        weights of the last evaluation (no second lookup): the rest point's own, or after a short
        last step (:data:`NEWTON_LAST_STEP`) the point's before it. ``offsets`` (k, 5, 5, 5, 3),
        or with no rows none: :func:`surface_offsets` added to the map, and ``moving_offsets`` to
        the velocity (blended with the last evaluation's cell, as the weights). ``table`` (k, 5, 5,
        5, 16 or 32), or with no rows none: :func:`blended_blocks` of the maps and offsets, then of
        ``moving`` and ``moving_offsets`` where ``moving`` has rows, read in the fine blocks in their
        place. Task i takes the rows of chunk ``(i * stride) % chunks`` (:func:`spread_stride`)."""
        field = (grid_joints, grid_weights, block_index, block_joints, block_weights)
        n = point.shape[0]
        chunk = NEWTON_CHUNK
        chunks = (n + chunk - 1) // chunk
        for task in numba.prange(chunks):
            first = (task * stride) % chunks
            f = np.empty(3)
            jac = np.empty((3, 3))
            f_trial = np.empty(3)
            jac_trial = np.empty((3, 3))
            inv = np.empty((3, 3))
            slot_of, touched, wsum, dsum = _gather_scratch(maps.shape[0])
            kept_joints = np.empty(8 * GRID_INFLUENCES, np.int64)  # the accepted point's weights
            kept_weights = np.empty(8 * GRID_INFLUENCES)
            blend = np.empty((4, BLENDED_CHANNELS))
            for p in range(first * chunk, min(n, first * chunk + chunk)):
                x = points[point[p]]
                y0, y1, y2 = start[p, 0], start[p, 1], start[p, 2]
                size, count, block, cx, cy, cz, tx, ty, tz = _newton_terms_one(
                    y0, y1, y2, x, maps, field, centre, radius, f, jac, slot_of, touched, wsum, dsum, offsets, table,
                    blend)
                kept = count
                kept_joints[:count] = touched[:count]
                kept_weights[:count] = wsum[:count]
                short = False
                for _ in range(iterations):
                    if size <= tolerance:
                        break
                    _inverse3(jac, inv)
                    s0 = -(inv[0, 0] * f[0] + inv[0, 1] * f[1] + inv[0, 2] * f[2])
                    s1 = -(inv[1, 0] * f[0] + inv[1, 1] * f[1] + inv[1, 2] * f[2])
                    s2 = -(inv[2, 0] * f[0] + inv[2, 1] * f[1] + inv[2, 2] * f[2])
                    length = math.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
                    if length <= last_step and _same_weight_cell(y0, y1, y2, y0 + s0, y1 + s1, y2 + s2, field,
                                                                 centre, radius):
                        y0, y1, y2 = y0 + s0, y1 + s1, y2 + s2  # taken without a new evaluation
                        short = True
                        break
                    shrink = min(1.0, max_step / max(length, 1e-300))
                    s0, s1, s2 = s0 * shrink, s1 * shrink, s2 * shrink
                    moved = False
                    for _h in range(halvings + 1):
                        trial, count, block_t, cx_t, cy_t, cz_t, tx_t, ty_t, tz_t = _newton_terms_one(
                            y0 + s0, y1 + s1, y2 + s2, x, maps, field, centre, radius, f_trial, jac_trial, slot_of,
                            touched, wsum, dsum, offsets, table, blend)
                        if trial < size:  # the terms at the new point are kept for the next step
                            y0, y1, y2 = y0 + s0, y1 + s1, y2 + s2
                            size = trial
                            f[:] = f_trial
                            jac[:] = jac_trial
                            block, cx, cy, cz, tx, ty, tz = block_t, cx_t, cy_t, cz_t, tx_t, ty_t, tz_t
                            kept = count
                            kept_joints[:count] = touched[:count]
                            kept_weights[:count] = wsum[:count]
                            moved = True
                            break
                        s0, s1, s2 = 0.5 * s0, 0.5 * s1, 0.5 * s2
                    if not moved:
                        break
                _inverse3(jac, inverse[p])
                rest[p, 0], rest[p, 1], rest[p, 2] = y0, y1, y2
                converged[p] = short or size <= tolerance
                d0, d1, d2 = y0 - start[p, 0], y1 - start[p, 1], y2 - start[p, 2]
                wild[p] = d0 * d0 + d1 * d1 + d2 * d2 > limit
                if moving.shape[0] and block >= 0 and table.shape[0]:
                    _table_blend(table, block, cx, cy, cz, tx, ty, tz, 0.0, 0.0, 0.0, blend, BLENDED_CHANNELS, False)
                    scale = 1.0 / max(blend[0, 12], 1e-12)
                    for a in range(3):
                        velocity[p, a] = ((blend[0, 4 * a] * y0 + blend[0, 4 * a + 1] * y1 + blend[0, 4 * a + 2] * y2
                                           + blend[0, 4 * a + 3]) * scale + blend[0, 13 + a])
                elif moving.shape[0]:
                    # As _blend_one then the velocity's product, in the same order: the same numbers.
                    total = 0.0
                    for s in range(kept):
                        total += kept_weights[s]
                    scale = 1.0 / max(total, 1e-12)
                    for a in range(3):
                        v = 0.0
                        for b in range(4):
                            value = 0.0
                            for s in range(kept):
                                value += kept_weights[s] * moving[kept_joints[s], a, b]
                            value *= scale
                            v += value * (y0 if b == 0 else y1 if b == 1 else y2 if b == 2 else 1.0)
                        velocity[p, a] = v
                    if block >= 0 and moving_offsets.shape[0]:
                        _add_blended_offset(velocity[p], moving_offsets, block, cx, cy, cz, tx, ty, tz)


def clamp_to_cube(rest: np.ndarray, lo: np.ndarray, hi: np.ndarray, fused: bool = True):
    """Rest points (m, 3) float64 clamped into the box ``lo``..``hi`` (3,) and rounded to float32
    (the network's input), and which rows were outside it: ``(clamped (m, 3) float32, outside
    (k,) int64)``. One numba pass (no float64 copies) when numba is there and ``fused``, else
    numpy."""
    if fused and _clamp_kernel is not None:
        clamped = np.empty(rest.shape, np.float32)
        flag = np.empty(len(rest), np.bool_)
        _clamp_kernel(np.ascontiguousarray(rest, np.float64), np.asarray(lo, np.float64), np.asarray(hi, np.float64),
                      clamped, flag)
        return clamped, np.flatnonzero(flag)
    inside = np.clip(rest, lo, hi)
    return inside.astype(np.float32), np.flatnonzero((rest != inside).any(axis=1))


def union_of_parts(distance: np.ndarray, point: np.ndarray, usable: np.ndarray, n: int,
                   fused: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The union over each point's parts: the least ``distance`` (m,) of its ``usable`` (m,) bool
    rows, the first in row order on a tie (rows sorted by joint, then point, as
    :func:`part_candidates` gives them: the lowest joint). ``point`` (m,) int64 indexes the n
    points. Returns ``(best (n,) float64, best_row (n,) int64)`` (+inf and 0 at a point with no
    usable row). One numba pass over the rows (:func:`_union_kernel`) when numba is there and
    ``fused``, else numpy joint by joint (the reference)."""
    best = np.full(n, np.inf)
    best_row = np.zeros(n, np.int64)
    if fused and _union_kernel is not None:
        _union_kernel(np.ascontiguousarray(distance), np.ascontiguousarray(point, np.int64),
                      np.ascontiguousarray(usable, np.bool_), best, best_row)
        return best, best_row
    rows = np.flatnonzero(usable)
    # Runs of rows of one joint: a point occurs once in each (part_candidates' order).
    starts = np.flatnonzero(np.diff(point[rows], prepend=np.iinfo(np.int64).max) <= 0)
    for lo, hi in zip(starts, [*starts[1:], len(rows)]):
        r = rows[lo:hi]
        d, at = distance[r], point[r]
        better = d < best[at]
        best[at[better]] = d[better]
        best_row[at[better]] = r[better]
    return best, best_row


def pull_back(gradient: np.ndarray, inverse: np.ndarray, row: np.ndarray, fused: bool = True) -> np.ndarray:
    """(n, 3) float64: the rest-frame gradients ``gradient`` (m, 3) of rows ``row`` (n,) int64
    pulled back to the posed frame through their maps ``inverse`` (m, 3, 3): ``inverse[r]^T
    gradient[r]``. One numba pass (no gathered copies) when numba is there and ``fused``, else
    numpy."""
    if fused and _pull_back_kernel is not None:
        out = np.empty((len(row), 3))
        _pull_back_kernel(np.ascontiguousarray(gradient), np.ascontiguousarray(inverse),
                          np.ascontiguousarray(row, np.int64), out)
        return out
    return np.einsum("na,nab->nb", gradient[row], inverse[row])


_union_kernel = _pull_back_kernel = _clamp_kernel = None
if grid_kernels.available():
    import numba

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _clamp_kernel(rest, lo, hi, clamped, flag):  # pragma: no cover
        """:func:`clamp_to_cube` over the rows (numba): ``clamped`` (m, 3) float32 and ``flag`` (m,)
        bool overwritten."""
        for p in numba.prange(rest.shape[0]):
            out = False
            for a in range(3):
                v = rest[p, a]
                c = min(max(v, lo[a]), hi[a])
                out = out or c != v
                clamped[p, a] = np.float32(c)
            flag[p] = out

    @numba.njit(cache=True, nogil=True)
    def _union_kernel(distance, point, usable, best, best_row):  # pragma: no cover
        """:func:`union_of_parts` in row order: ``best`` (n,) +inf and ``best_row`` (n,) updated."""
        for r in range(point.shape[0]):
            if usable[r]:
                p = point[r]
                if distance[r] < best[p]:
                    best[p] = distance[r]
                    best_row[p] = r

    @numba.njit(cache=True, nogil=True, parallel=True)
    def _pull_back_kernel(gradient, inverse, row, out):  # pragma: no cover
        """:func:`pull_back` over the points (numba): ``out`` (n, 3) overwritten."""
        for p in numba.prange(row.shape[0]):
            r = row[p]
            for b in range(3):
                out[p, b] = gradient[r, 0] * inverse[r, 0, b] + gradient[r, 1] * inverse[r, 1, b] \
                    + gradient[r, 2] * inverse[r, 2, b]


def part_labels(skin: Skin, centre, radius: float, resolution: int, band: float) -> np.ndarray:
    """(R, R, R) uint8: the label grid of ``skin``'s rest pose over the cube ``centre +-
    radius``: each cell's centre takes the dominant joint (largest weight) of its nearest rest
    vertex, or :data:`NO_PART` where it lies more than ``band`` (collider units) outside the rest
    surface."""
    from scipy.spatial import cKDTree

    from ..meshes import ExactSDF, Mesh

    axis = (np.arange(resolution) + 0.5) / resolution * 2.0 - 1.0
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    cells = np.asarray(centre, np.float64) + radius * grid
    owner = skin.joints[np.arange(len(skin.joints)), np.argmax(skin.weights, axis=1)]
    _, nearest = cKDTree(skin.vertices).query(cells)
    labels = owner[nearest].astype(np.uint8)
    distance, _, _ = ExactSDF(Mesh(skin.vertices, skin.faces, "rest")).query(cells)
    labels[distance > band] = NO_PART
    return labels.reshape(resolution, resolution, resolution)


def part_boxes(skin: Skin, pad: float) -> np.ndarray:
    """(J, 2, 3) float64: per joint the box (lo, hi) of the rest vertices it dominates, padded by
    ``pad`` (collider units); a joint that dominates none gets the whole rest box."""
    owner = skin.joints[np.arange(len(skin.joints)), np.argmax(skin.weights, axis=1)]
    boxes = np.empty((skin.skeleton.joint_count, 2, 3))
    for j in range(len(boxes)):
        mine = skin.vertices[owner == j]
        if not len(mine):
            mine = skin.vertices
        boxes[j] = mine.min(axis=0) - pad, mine.max(axis=0) + pad
    return boxes


# --------------------------------------------------------------------------------------------
# The network


def build_articulated_network(arch: ArticulatedGridArchitecture, centre, radius: float):
    """The torch module of ``arch`` (``centre``, ``radius``: the rest pose's normalisation, as
    the static network's). ``value_and_gradient(rest, joint, code)``: distance (m,) and its
    gradient in the rest frame (m, 3) at rest-frame points (m, 3) float32 of parts ``joint`` (m,)
    int64 with pose codes ``code`` (m, 9 * slots) float32."""
    import torch
    from torch import nn

    class ArticulatedSDF(nn.Module):
        def __init__(self):
            super().__init__()
            self.grid = build_grid_network(arch.grid(), centre, radius)
            width = arch.hidden_width
            self.embedding = nn.Parameter(torch.zeros(arch.joints, width))
            self.condition = nn.Parameter(torch.zeros(width, arch.code_width()))
            r = arch.label_resolution
            self.register_buffer("labels", torch.full((r, r, r), NO_PART, dtype=torch.uint8))
            if arch.label_dilation:  # the parts each code of the label grid names (dilated_labels)
                self.register_buffer("label_sets", torch.zeros(256, arch.joints, dtype=torch.bool))
            self.register_buffer("part_boxes", torch.zeros(arch.joints, 2, 3, dtype=torch.float64))
            side = (arch.weight_resolution + 1, ) * 3 + (GRID_INFLUENCES,)
            self.register_buffer("weight_joints", torch.zeros(side, dtype=torch.uint8))
            self.register_buffer("weight_values", torch.zeros(side, dtype=torch.uint8))
            blocks = arch.fine_weight_resolution // BLOCK_CELLS
            self.register_buffer("weight_block_index", torch.full((blocks,) * 3, -1, dtype=torch.int32))
            block = (arch.weight_blocks,) + (BLOCK_CELLS + 1,) * 3 + (GRID_INFLUENCES,)
            self.register_buffer("weight_block_joints", torch.zeros(block, dtype=torch.uint8))
            self.register_buffer("weight_block_values", torch.zeros(block, dtype=torch.uint8))

        def set_weight_field(self, field: WeightField):
            """Take the weight field's arrays (:func:`weight_field`, shaped as the architecture)."""
            for name, value in zip(WEIGHT_FIELD_BUFFERS, field):
                getattr(self, name).copy_(torch.from_numpy(np.ascontiguousarray(value)))

        def set_rest_tables(self, labels: np.ndarray, sets: np.ndarray | None, boxes: np.ndarray,
                            field: WeightField):
            """Take the rest pose's tables: the label grid (:func:`dilated_labels`' with its ``sets``
            where the architecture dilates it), the part boxes and the weight field."""
            self.labels.copy_(torch.from_numpy(labels))
            if arch.label_dilation:
                self.label_sets.copy_(torch.from_numpy(sets))
            self.part_boxes.copy_(torch.from_numpy(boxes))
            self.set_weight_field(field)

        @property
        def radius(self):
            return self.grid.radius

        def first_bias(self, joint, code):
            """The first layer's added bias of parts ``joint`` at codes ``code``: (m, H)."""
            return self.embedding[joint] + code @ self.condition.T

        def forward(self, rest, joint, code):
            u = (rest - self.grid.centre) / self.grid.radius
            features, _ = self.grid.encode_parts(u, False)
            distance, _ = self.grid.head(features, self.first_bias(joint, code))
            return distance

        def value_and_gradient(self, rest, joint, code):
            u = (rest - self.grid.centre) / self.grid.radius
            features, jacobian = self.grid.encode_parts(u, True)
            distance, g = self.grid.head(features, self.first_bias(joint, code))
            return distance, torch.einsum("nlf,nlfd->nd", g, jacobian)

    return ArticulatedSDF()


class PreparedPose(NamedTuple):
    """A query's pose prepared once (:meth:`ArticulatedNeuralCollider.pose`): ``to_rest`` (J, 3,
    4) and ``posed`` (J, 4, 4) (:func:`rest_maps`), ``moving`` (J, 3, 4) the maps' motion
    ``dA/dt`` or None (still), ``bias`` (J, H) float32 the parts' first biases, ``offsets`` and
    ``moving_offsets`` the :func:`surface_offsets` of ``posed`` and ``moving`` (or None: an
    architecture without them, or still), ``surface`` the posed skin the exact patches answer on
    (:func:`~.patches.posed_surface`; None without patches)."""

    to_rest: np.ndarray
    posed: np.ndarray
    moving: np.ndarray | None
    bias: np.ndarray
    offsets: np.ndarray | None
    moving_offsets: np.ndarray | None
    surface: PosedSurface | None


class PatchedRows(NamedTuple):
    """A group's rows after the exact patches (:func:`~.patches.answer_on_patches`): ``distance``
    (m,) (the patch's where it answered, else the network's), ``normal`` (m, 3) and ``velocity``
    (m, 3) or None, collider frame, and ``face`` (m,) (-1: the network's answer stands)."""

    distance: np.ndarray
    normal: np.ndarray
    velocity: np.ndarray | None
    face: np.ndarray

    def take(self, rows: np.ndarray, network: np.ndarray, name: str) -> np.ndarray:
        """``network`` (r, 3), the ``name`` (normal or velocity) of ``rows`` (r,), with the
        patches' where they answered."""
        answered = self.face[rows] >= 0
        network[answered] = getattr(self, name)[rows[answered]]
        return network


def architecture_of(info: ColliderInfo) -> ArticulatedGridArchitecture:
    """The architecture in ``info.settings["architecture"]``; ValueError if there is none."""
    try:
        return ArticulatedGridArchitecture(**info.settings["architecture"])
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"neural-skinned settings lack a valid articulated architecture: {exc}") from None


class ArticulatedNeuralCollider(Collider):
    """A trained :func:`build_articulated_network` and the skin it was trained on
    (``info.settings["architecture"]``, ``info.skeleton`` and ``info.settings["channels"]`` as
    the exact kind's)."""

    kind = "neural-skinned"
    chunk_points = 524_288
    clamps_to_domain = False  # every answer goes through a part's rest frame (its own box rule)

    def __init__(self, info: ColliderInfo, skin: Skin, network, device: str | None = None, keep: int = 4,
                 patches: bool = True):
        """``patches``: answer near the skin exactly (:mod:`.patches`: the points in its clean
        cells by the posed skin itself, the others' rows by the patches about the network's closest
        points; False: the network alone, as the model files before them were answered)."""
        super().__init__(info)
        import torch

        self._torch = torch
        self._device = resolve_device(device)
        self.skin = skin
        self.arch = architecture_of(info)
        if self.arch.joints != skin.skeleton.joint_count:
            raise ValueError(f"the network has {self.arch.joints} parts, the skeleton "
                             f"{skin.skeleton.joint_count} joints")
        self.loop = bool(info.skeleton.get("loop", True))
        self.network = network.to(self._device).eval()
        for parameter in self.network.parameters():
            parameter.requires_grad_(False)
        self.labels = self.network.labels.cpu().numpy()
        self.part_boxes = self.network.part_boxes.cpu().numpy()
        self.weights = WeightField(*(np.ascontiguousarray(getattr(self.network, name).cpu().numpy())
                                     for name in WEIGHT_FIELD_BUFFERS))
        sets = self.network.label_sets.cpu().numpy() if self.arch.label_dilation else None
        self.allowed = allowed_labels(skin.skeleton.parents, self.arch.neighbours, sets)
        grid = self.network.grid
        self.centre = grid.centre.double().cpu().numpy()
        self.radius = float(grid.radius)
        #: The label grid's part boxes at rest (pose-independent; each query poses them).
        self.rest_boxes = label_boxes(self.labels, self.centre, self.radius, self.allowed)
        #: Where the fine blocks' corners meet the rest surface (the surface offsets' anchors).
        self.anchors = (surface_anchors(skin, self.weights, self.centre, self.radius)
                        if self.arch.surface_offsets else None)
        #: The exact patches' cells of the rest mesh and the band they answer in (collider
        #: units), or None: the network answers everywhere.
        self.patches: PatchCells | None = None
        self.patch_band = 0.0
        #: The fewest points of a query answered within the band of the posed skin by its pose's
        #: cells (:meth:`near_cells`; :func:`~.patches.near_points`), or None: every query through
        #: the network and its patches.
        self.near_points: int | None = near_points(self.chunk_points) if patches else None
        self._near_cell = 0.0
        if patches:
            finest = 2.0 * self.radius / self.arch.max_resolution
            self.patches = patch_cells(skin.vertices, skin.faces, PATCH_REACH * finest, PATCH_CELL * finest)
            self.patch_band = PATCH_BAND * finest
            self._near_cell = NEAR_CELL * finest
            self._edges = edge_index(np.asarray(skin.faces, np.int64))  # the posed surfaces' pseudo-normals
        self._cache: Kept[PreparedPose] = Kept(keep)
        self._near: Kept[NearCells] = Kept(keep)  # the last poses' cells
        self._table: tuple | None = None  # (prepared pose, with the motion, its pose_table)
        self._lock = threading.Lock()

    @property
    def device(self) -> str:
        return self._device

    @property
    def skinned(self) -> bool:
        return True

    def pose(self, time, skeleton) -> PreparedPose:
        """The query's pose prepared once (cached by pose: :class:`PreparedPose`)."""
        key = pose_key(time, skeleton)
        return self._cache.get(key, lambda: self._prepare(key, skeleton))

    def _prepare(self, key: tuple, skeleton) -> PreparedPose:
        transforms, velocities = resolve_pose(self.skin, self.loop, key, skeleton)
        to_rest, posed = rest_maps(self.skin.skeleton, transforms)
        moving = None
        if velocities is not None:
            moving = (np.asarray(velocities, np.float64) @ self.skin.skeleton.inverse_bind)[:, :3, :]
            # The velocity at a posed point x: dA_j/dt @ A_j^-1 x = moving_j @ [x_j, 1].
        codes = pose_codes(self.skin.skeleton, transforms, self.arch.pose_slots)
        torch = self._torch
        with torch.inference_mode():
            joints = torch.arange(self.arch.joints, device=self._device)
            bias = self.network.first_bias(joints, torch.from_numpy(codes).to(self._device))
        offsets = moving_offsets = None
        if self.anchors is not None:
            if moving is None:
                offsets = surface_offsets(self.anchors, self.weights, self.skin, posed[:, :3, :])
            else:  # the pose's and its motion's in one pass
                offsets, moving_offsets = surface_offsets(self.anchors, self.weights, self.skin,
                                                          np.stack([posed[:, :3, :], moving]))
        surface = None
        if self.patches is not None:
            surface = posed_surface(skin_vertices(self.skin, transforms), self.skin.faces, self._edges,
                                    None if velocities is None else skin_velocities(self.skin, transforms, velocities))
        return PreparedPose(to_rest, posed, moving, bias.float().cpu().numpy(), offsets, moving_offsets, surface)

    def near_cells(self, time, skeleton) -> NearCells:
        """The :class:`~.patches.NearCells` of a pose (``time`` / ``skeleton`` as
        :meth:`evaluate_at`'s): the posed skin's cells within :attr:`patch_band` of it, clean where
        every face listed lies wholly on the exact kind's surface (its union's boundary, by the exact
        kind's own rule: the skin may pass through itself). Built on first use
        (:func:`~.patches.pose_cells`) and kept for the last ``keep`` poses."""
        return self._near.get(pose_key(time, skeleton), lambda: pose_cells(
            self.pose(time, skeleton).surface, self.skin.faces, self._edges, self.patch_band, self._near_cell))

    @property
    def gradient_in_one_pass(self) -> bool:  # type: ignore[override]
        """With the exact patches the gradient costs little beside the distance (the patches take
        every row's anyway), and one pass answers a point's distance and normal by one rule."""
        return self.patches is not None

    def evaluate(self, local, want_gradient):
        distance, gradient, _ = self.evaluate_at(local, want_gradient, None, None)
        return distance, gradient

    def parts_at(self, local: np.ndarray, time, skeleton=None):
        """:func:`parts_through_skinning` of points ``local`` (n, 3) (collider frame) at a pose
        (``time`` / ``skeleton`` as :meth:`evaluate_at`'s), by this model's rule, weights and
        offsets: the rows the query's union takes, ``(point, joint, rest, inverse)``."""
        prepared = self.pose(time, skeleton)
        return parts_through_skinning(local, prepared.to_rest, prepared.posed, self.labels, self.centre, self.radius,
                                      self.allowed, self.part_boxes, self.weights, self.arch.skinning_iterations,
                                      self.arch.skinning_solver, self.arch.candidate_rule, offsets=prepared.offsets)

    def kept_table(self, prepared: PreparedPose, moving: np.ndarray | None) -> np.ndarray:
        """:func:`pose_table` of a prepared pose (with its motion where ``moving``), built once and
        kept for the last pose asked: a query of many points answers each of its chunks, and its
        retried rows, through one (the walker's: 29 MB with the motion; building one costs 2-30 ms,
        the most where its memory is new)."""
        with self._lock:
            kept = self._table
        if kept is not None and kept[0] is prepared and kept[1] == (moving is not None):
            return kept[2]
        table = pose_table(self.weights, prepared.posed, moving, prepared.offsets,
                           None if moving is None else prepared.moving_offsets)
        with self._lock:
            self._table = (prepared, moving is not None, table)
        return table

    def evaluate_at(self, local, want_gradient, time, skeleton=None):
        """A query of :attr:`near_points` or more points: those within the band of the skin in its
        pose's clean cells by the posed skin itself (:meth:`near_cells`), the others through the
        network; a smaller query (a pose's cells cost more than they save there) all through the
        network (:meth:`_through_network`), whose exact patches answer nearly every point near the
        skin alike."""
        prepared = self.pose(time, skeleton)
        if self.patches is None or self.near_points is None or len(local) < self.near_points:
            return self._through_network(local, want_gradient, prepared)
        return answer_near_first(local, self.near_cells(time, skeleton), prepared.surface, self.skin.faces,
                                 want_gradient, lambda rows, gradient: self._through_network(rows, gradient, prepared))

    def _through_network(self, local: np.ndarray, want_gradient: bool, prepared: PreparedPose):
        """:meth:`evaluate_at` of points ``local`` through the network at a prepared pose: each
        point's candidate parts, their rows' rest points, the network there (and the exact patches
        about its closest points), the union over the parts."""
        to_rest, posed, moving, bias, offsets, moving_offsets, surface = prepared
        if self.patches is None:
            surface = None  # the network alone (patches turned off after the pose was prepared)
        if not want_gradient:
            moving = None  # no velocity asked
        table = None
        if self.arch.skinning_solver == "newton" and self.arch.skinning_iterations and uses_table(len(local),
                                                                                                 self.weights):
            table = self.kept_table(prepared, moving)
        groups = [group for group in candidate_groups_through_skinning(
            local, to_rest, posed, self.labels, self.centre, self.radius, self.allowed, self.part_boxes, self.weights,
            self.arch.skinning_iterations, self.arch.skinning_solver, self.arch.candidate_rule, moving=moving,
            rest_boxes=self.rest_boxes, offsets=offsets, moving_offsets=moving_offsets, table=table)
            if group is not None]
        n = len(local)
        # Every row goes through the network (the few dropped ones too: cheaper than copies of the rows);
        # the exact patches need each row's gradient (its closest point) even where none is asked.
        values = [self._part_values(g.rows.rest, g.joint, bias, want_gradient or surface is not None)
                  for g in groups]
        patched = [None if surface is None else self._on_patches(local, g, d, gradient, surface)
                   for g, (d, gradient) in zip(groups, values)]
        distances = [d if p is None else p.distance for (d, _), p in zip(values, patched)]
        # The union over each group; a point's usable rows are all in one group (the retried rows of
        # the points whose retry reached a root, else the first), so the groups' unions never compete.
        unions = [union_of_parts(d, g.point, g.rows.usable, n) for g, d in zip(groups, distances)]
        best, best_row = unions[0]
        retried = None
        if len(unions) > 1:
            retried = np.flatnonzero(unions[1][0] < best)
            best[retried] = unions[1][0][retried]
        if not want_gradient:
            return best, None, None

        def chosen(take):
            """(n, ...): ``take(i, rows)`` of group i at each point's chosen row."""
            out = take(0, best_row)
            if retried is not None and len(retried):
                out[retried] = take(1, unions[1][1][retried])
            return out

        def normals(i, rows):
            """Group i's rows' normals: the patch's where it answered, else the network's gradient
            through the map to the rest pose: grad_x f(B x) = B^T grad f (B: the part's rigid map,
            or the skinning's inverse at the point)."""
            out = pull_back(values[i][1], groups[i].rows.inverse, rows)
            return out if patched[i] is None else patched[i].take(rows, out, "normal")

        g = chosen(normals)
        if moving is None:
            return best, g, None

        def velocity_of(i, rows, network):
            """Group i's rows' velocities: the patch's closest point's where it answered, else
            ``network``'s (r, 3)."""
            return network if patched[i] is None else patched[i].take(rows, network, "velocity")

        if all(group.rows.velocity is not None for group in groups):  # the Newton kernel's, at the rest point
            return best, g, chosen(lambda i, rows: velocity_of(i, rows, groups[i].rows.velocity[rows]))
        rest = chosen(lambda i, rows: groups[i].rows.rest[rows])
        if self.arch.skinning_iterations:  # the skinning's motion at the rest point: sum_k w_k dA_k/dt
            velocity = _velocity_at(rest, moving, self.weights, self.centre, self.radius, moving_offsets)
        else:  # the chosen part's rigid motion
            homogeneous = np.concatenate([rest, np.ones((n, 1))], axis=1)
            velocity = np.einsum("nab,nb->na", moving[chosen(lambda i, rows: groups[i].joint[rows])], homogeneous)
        if surface is None:
            return best, g, velocity
        on_patches = chosen(lambda i, rows: velocity_of(i, rows, np.full((len(rows), 3), np.nan)))
        return best, g, np.where(np.isnan(on_patches), velocity, on_patches)

    def _on_patches(self, local: np.ndarray, group: CandidateRows, distance: np.ndarray, gradient: np.ndarray,
                    surface: PosedSurface) -> PatchedRows:
        """``group``'s rows answered on the exact patches (:func:`~.patches.answer_on_patches`)
        where the network (``distance`` (m,), rest-frame ``gradient`` (m, 3)) puts them within
        :attr:`patch_band` of the skin."""
        return PatchedRows(*answer_on_patches(local, group.point, group.rows.rest, distance, gradient,
                                              self.patch_band, self.patches, surface, self.skin.faces))

    def _part_values(self, rest: np.ndarray, joint: np.ndarray, bias: np.ndarray, want_gradient: bool):
        """Distance (m,) and rest-frame gradient (m, 3) (or None) at rest-frame points (m, 3)
        float64 of parts ``joint`` (m,) int64, the parts' first biases ``bias`` (J, H) float32
        (one network call for all parts: the fused kernel takes each point's bias by its part),
        with the conservative box rule beyond the grid's cube: the value at the cube's nearest
        point plus the way there (the normal along it); and where a row's gradient vanishes (a
        plateau), the neural kinds' central differences in its part (``across_plateaus``)."""
        torch = self._torch
        lo, hi = self.centre - self.radius, self.centre + self.radius
        clamped, outside = clamp_to_cube(rest, lo, hi)
        x = torch.as_tensor(clamped, device=self._device)
        grid = self.network.grid
        if grid.can_fuse(x):
            threads = torch.get_num_threads()
            grid_kernels.set_threads(threads)
            try:
                d, g = grid.fused_query(x, want_gradient, bias, joint)
            finally:
                if torch.get_num_threads() != threads:
                    torch.set_num_threads(threads)  # numba's OpenMP pool resets it (neural.py)
        else:
            with torch.inference_mode():
                rows = torch.as_tensor(joint, device=self._device)
                code_bias = torch.as_tensor(bias, device=self._device)[rows]
                u = (x - grid.centre) / grid.radius
                features, jacobian = grid.encode_parts(u, want_gradient)
                d, gf = grid.head(features, code_bias)
                g = torch.einsum("nlf,nlfd->nd", gf, jacobian) if want_gradient else None
        d = d.double().cpu().numpy()
        g = g.double().cpu().numpy() if want_gradient else None
        if len(outside):
            away = rest[outside] - np.clip(rest[outside], lo, hi)
            gap = np.linalg.norm(away, axis=1)
            d[outside] = np.maximum(d[outside], 0.0) + gap
            if want_gradient:
                g[outside] = away / gap[:, None]
        if want_gradient:  # the neural kinds' rule where a plateau's gradient vanishes, each row in its part
            step = float(grid.radius) / self.arch.max_resolution
            g = across_plateaus(rest, g, lambda rows, probes: self._part_values(
                probes, np.repeat(joint[rows], 6), bias, False)[0], step, lo, hi)
        return d, g

    def tensors(self):
        out = skin_tensors(self.skin)
        state = {k: v.detach().cpu().numpy() for k, v in self.network.state_dict().items()}
        state.update({f"grid.{k}": v for k, v in pack_table(state.pop("grid.table"), self.arch.grid()).items()})
        out.update({NETWORK_PREFIX + k: v for k, v in state.items()})
        return out

    @classmethod
    def from_tensors(cls, info, tensors, device=None):
        import torch

        arch = architecture_of(info)
        skin = skin_from_tensors(info, {k: v for k, v in tensors.items() if not k.startswith(NETWORK_PREFIX)})
        state = {k[len(NETWORK_PREFIX):]: v for k, v in tensors.items() if k.startswith(NETWORK_PREFIX)}
        grid = unpack_table({k[len("grid."):]: v for k, v in state.items() if k.startswith("grid.table")},
                            arch.grid())
        state = {k: v for k, v in state.items() if not k.startswith("grid.table")}
        state["grid.table"] = grid["table"]
        with torch.random.fork_rng(devices=[]):  # leave the caller's random stream as it was
            network = build_articulated_network(arch, np.zeros(3), 1.0)
        if not arch.weight_blocks and not arch.fine_weight_resolution:  # files from before the fine field
            for name in WEIGHT_FIELD_BUFFERS[2:]:
                state.setdefault(name, getattr(network, name).numpy())
        expected = {k: tuple(v.shape) for k, v in network.state_dict().items()}
        found = {k: tuple(np.shape(v)) for k, v in state.items()}
        if expected != found:
            raise ValueError(f"weights do not match the architecture {asdict(arch)}: "
                             f"expected {expected}, found {found}")
        network.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()})
        return cls(info, skin, network, device)
