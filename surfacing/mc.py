"""Marching cubes over the block-sparse color field, in Taichi (see surfacing/mc_table.py).

One vertex per grid edge the iso level crosses, owned by the edge's lower node: the vertices
come out welded (no sort, no hashing), numbered block by block, and the triangles refer to
them directly. Four kernels, each parallel over blocks and serial inside one:

1. count_vertices: per block of the band (the blocks whose cells cross the level and their
   upper neighbours: every crossed edge's lower node lies in one), each node's crossed edges
   (3 bits) and how many the nodes before it own (node_first);
2. place_vertices: the vertex on each such edge, in metres: its block's first node (in
   float64 on the host, rounded once) plus its place in the block. The place along the edge
   is where the linear interpolation of color^power between the edge's nodes reaches
   iso^power (power 1: plain linear interpolation). An anisotropic field (power 1/3) falls to
   its iso within about two cells, as the cube of the distance to its kernels' edge (the
   spline kernels' tails, (1 - q)^3, squashed along the normal). Interpolated linearly, its
   vertices stood out where the surface lay between two grid planes and not where it met
   one, so a surface tilted against the grid came out in terraces a cell apart in height
   (0.9 mm rms on the example's falling column, bench/RESULTS.md); its cube root is about
   linear there;
3. count_triangles: per block whose cells cross the level, each cell's case and the block's
   triangle count;
4. emit_triangles: each cell's triangles from the table, a vertex id being node_first of the
   edge's owner node plus its crossed edges along lower axes.

place_vertices also interpolates each vertex's velocity along its edge, when the field has
one. Block-level offsets between the passes are numpy prefix sums over a few thousand numbers;
the per-node arrays stay on the device, and the color is read where the splat wrote it.
vertex_normals, for any triangle mesh, is here too, in parallel and deterministic.
"""
import numpy as np
import taichi as ti

from solver.neighbours import sort_run
from solver.types import F2, I1, V3

from . import device as D
from .device import I2, I3, R8, U2
from .grid import B
from .mc_table import EDGE_AXIS, EDGE_CORNER, table

B3 = B * B * B


@ti.func
def _at(color: ti.template(), idx):
    """Node idx (block * 512 + node) of the color's rows of 8."""
    return color[idx >> 3][idx & 7]


@ti.func
def _value(color: ti.template(), nbr: ti.template(), s, x, y, z):
    """The color at node (x, y, z), each in 0..8, of block row s of `nbr` (column 0: the block
    itself; column bx + 2 by + 4 bz: the upper neighbour the node falls in, the zero block if
    none)."""
    blk = nbr[s, (x >> 3) + 2 * (y >> 3) + 4 * (z >> 3)]
    return _at(color, blk * B3 + ((x & 7) * B + (y & 7)) * B + (z & 7))


@ti.func
def _edges(color: ti.template(), nbr: ti.template(), s, n, iso):
    """The crossed edges of node n of block row s, as bits (1: +x, 2: +y, 4: +z)."""
    x, y, z = n >> 6, (n >> 3) & 7, n & 7
    base = nbr[s, 0] * B3
    inside = _at(color, base + n) > iso
    bits = 0
    # the node one step up each axis: in the block, or at the bottom of the upper neighbour
    ox = base + n + B * B if x < 7 else nbr[s, 1] * B3 + n - 7 * B * B
    oy = base + n + B if y < 7 else nbr[s, 2] * B3 + n - 7 * B
    oz = base + n + 1 if z < 7 else nbr[s, 4] * B3 + n - 7
    if (_at(color, ox) > iso) != inside:
        bits |= 1
    if (_at(color, oy) > iso) != inside:
        bits |= 2
    if (_at(color, oz) > iso) != inside:
        bits |= 4
    return bits


@ti.kernel
def count_vertices(color: R8, nbr: I2, iso: ti.f32, edges: U2, node_first: I2, count: I1):
    """edges[s, n]: node n's crossed edges (bits, see _edges) in band block row s;
    node_first[s, n]: the crossed edges of the nodes before it; count[s]: all of the row's."""
    for s in count:
        c = 0
        for n in range(B3):
            bits = _edges(color, nbr, s, n, iso)
            edges[s, n] = ti.cast(bits, ti.u8)
            node_first[s, n] = c
            c += (bits & 1) + (bits >> 1 & 1) + (bits >> 2)
        count[s] = c


@ti.kernel
def place_vertices(color: R8, nbr: I2, iso: ti.f32, power: ti.f32, offset: I1, edges: U2, node_first: I2,
                   origin: F2, cell: ti.f32, points: V3, vnbr: I2, velocity: V3, vertex_velocity: V3,
                   with_velocity: ti.template()):
    """points[v]: vertex v (where color^power, linear along its edge, reaches iso^power), its
    block row's first node origin[s] plus its place in the block, in metres; node_first
    becomes global (adds offset[s]). With velocity (node-major vectors, vnbr[s, col]: where
    the velocity of nbr[s, col]'s block is), vertex_velocity[v] the linear interpolation of
    the edge's nodes' velocities at the same place."""
    lifted_iso = ti.pow(iso, power)
    for s in offset:
        for n in range(B3):
            v = offset[s] + node_first[s, n]
            node_first[s, n] = v
            bits = ti.cast(edges[s, n], ti.i32)
            if bits:
                x, y, z = n >> 6, (n >> 3) & 7, n & 7
                c0 = _value(color, nbr, s, x, y, z)
                for a in ti.static(range(3)):
                    if bits >> a & 1:
                        c1 = _value(color, nbr, s, x + int(a == 0), y + int(a == 1), z + int(a == 2))
                        t = (iso - c0) / (c1 - c0)
                        if power != 1.0:    # (two nodes a float apart may lift to one value: keep t then)
                            g0 = ti.pow(ti.max(c0, 0.0), power)
                            dg = ti.pow(ti.max(c1, 0.0), power) - g0
                            if dg != 0.0:
                                t = ti.math.clamp((lifted_iso - g0) / dg, 0.0, 1.0)
                        local = ti.math.vec3(x, y, z)
                        local[a] += t
                        points[v] = ti.math.vec3(origin[s, 0], origin[s, 1], origin[s, 2]) + cell * local
                        if ti.static(with_velocity):
                            u0 = velocity[vnbr[s, 0] * B3 + n]
                            x1, y1, z1 = x + int(a == 0), y + int(a == 1), z + int(a == 2)
                            col = (x1 >> 3) + 2 * (y1 >> 3) + 4 * (z1 >> 3)
                            u1 = velocity[vnbr[s, col] * B3 + ((x1 & 7) * B + (y1 & 7)) * B + (z1 & 7)]
                            vertex_velocity[v] = (1.0 - t) * u0 + t * u1
                        v += 1


@ti.func
def _case(color: ti.template(), nbr: ti.template(), s, n, iso):
    """The case (bit v: corner v above iso) of the cell whose lowest corner is node n."""
    i, j, k = n >> 6, (n >> 3) & 7, n & 7
    case = 0
    if i < 7 and j < 7 and k < 7:                       # all eight corners in the block
        base = nbr[s, 0] * B3 + n
        for v in ti.static(range(8)):
            if _at(color, base + (v & 1) * B * B + (v >> 1 & 1) * B + (v >> 2 & 1)) > iso:
                case |= 1 << v
    else:
        for v in ti.static(range(8)):
            if _value(color, nbr, s, i + (v & 1), j + (v >> 1 & 1), k + (v >> 2 & 1)) > iso:
                case |= 1 << v
    return case


@ti.kernel
def count_triangles(color: R8, nbr: I2, iso: ti.f32, tri_count: I1, cases: U2, count: I1):
    """cases[s, n]: the case of cell n of block row s; count[s]: the row's triangles."""
    for s in count:
        c = 0
        for n in range(B3):
            case = _case(color, nbr, s, n, iso)
            cases[s, n] = ti.cast(case, ti.u8)
            c += tri_count[case]
        count[s] = c


@ti.kernel
def emit_triangles(cases: U2, slot: I2, tri_edges: I3, tri_count: I1, edge_corner: I1,
                   edge_axis: I1, offset: I1, edges: U2, node_first: I2, faces: I2):
    """faces[offset[s]:]: the triangles of block row s's cells as vertex ids. slot[s, col]: the
    band row of the block in column col (as nbr). A vertex is node_first[owner row, owner node]
    plus the owner node's crossed edges along lower axes."""
    for s in offset:
        f = offset[s]
        for n in range(B3):
            case = ti.cast(cases[s, n], ti.i32)
            if tri_count[case]:
                i, j, k = n >> 6, (n >> 3) & 7, n & 7
                for t in range(tri_count[case]):
                    for q in ti.static(range(3)):
                        e = tri_edges[case, t, q]
                        lo = edge_corner[e]
                        x, y, z = i + (lo & 1), j + (lo >> 1 & 1), k + (lo >> 2 & 1)
                        owner = slot[s, (x >> 3) + 2 * (y >> 3) + 4 * (z >> 3)]
                        m = ((x & 7) * B + (y & 7)) * B + (z & 7)
                        below = ti.cast(edges[owner, m], ti.i32) & ((1 << edge_axis[e]) - 1)
                        faces[f, q] = node_first[owner, m] + (below & 1) + (below >> 1)
                    f += 1


@ti.kernel
def k_face_normals(points: V3, faces: I2, normal: V3, count: I1):
    """normal[f] = e1 x e2 of face f (twice its area, along its normal); count[v] += the faces at v."""
    for f in range(normal.shape[0]):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        p = points[a]
        normal[f] = (points[b] - p).cross(points[c] - p)
        for q in ti.static(range(3)):
            ti.atomic_add(count[faces[f, q]], 1)


@ti.kernel
def k_incident(faces: I2, start: I1, fill: I1, incident: I1):
    """incident[start[v] ...]: the faces at vertex v (in no particular order yet)."""
    for f in range(faces.shape[0]):
        for q in ti.static(range(3)):
            v = faces[f, q]
            incident[start[v] + ti.atomic_add(fill[v], 1)] = f


@ti.kernel
def k_gather_normals(start: I1, count: I1, incident: I1, normal: V3, out: V3):
    """out[v] = the unit sum of the normals of v's faces, summed in face order (each vertex's
    few faces are insertion-sorted first): the same sums on every run and backend, and the
    same as one thread adding face after face."""
    for v in out:
        s0, n = start[v], count[v]
        sort_run(incident, s0, n)
        acc = ti.math.vec3(0.0)
        for a in range(n):
            acc += normal[incident[s0 + a]]
        out[v] = acc / ti.max(acc.norm(), 1e-30)


def normals_on_device(points, faces, n_points: int, n_faces: int):
    """Area-weighted unit vertex normals of a mesh already on the device, as a device array: a
    gather per vertex over a vertex-to-face table (count, scan, fill, sort), in parallel."""
    out = D.zeros(ti.f32, n_points, 3)
    if n_faces == 0:
        return out
    normal = D.empty(ti.f32, n_faces, 3)
    count = D.zeros(ti.i32, n_points)
    k_face_normals(points, faces, normal, count)
    start, total = D.exclusive_scan(count, n_points)
    incident = D.empty(ti.i32, total)
    k_incident(faces, start, D.zeros(ti.i32, n_points), incident)
    k_gather_normals(start, count, incident, normal, out)
    return out


def vertex_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V, 3) float32 outward unit vertex normals from the faces' winding (area-weighted)."""
    if len(faces) == 0:
        return np.zeros((len(points), 3), np.float32)
    out = normals_on_device(D.vec3s(points), _faces(faces), len(points), len(faces))
    return D.host(out)[:len(points)]


def _faces(faces: np.ndarray):
    return D.upload(np.asarray(faces).reshape(-1, 3))


def marching_cubes(rows, upper: np.ndarray, blocks: np.ndarray, todo: np.ndarray, iso: float, cell: float,
                   velocity=None, velocity_slot: np.ndarray | None = None, power: float = 1.0):
    """(points, faces, vertex_velocity, points_dev, faces_dev): the `iso` surface of a
    block-sparse field of node spacing `cell` as vertices in metres (float32), triangles
    (int32) counter-clockwise seen from the side below `iso` (outward for a fluid whose color
    is above it), the vertices' velocities (float32, zero without a velocity field), and the
    vertices and triangles on the device.

    rows: the color on the device (rows of 8 nodes, the last block all zero); upper: (nb + 1,
    8) each block and its upper neighbours at block offsets CORNER[1:] (Field.upper); blocks:
    (nb, 3) block coordinates; todo: the blocks that own a cell crossing `iso` (a superset will
    do). velocity: node-major vectors on the device, velocity_slot (nb + 1,) where each
    block's are. power: the vertices sit where color^power, linear along their edges, reaches
    iso^power (1: linear interpolation of the color; see place_vertices)."""
    nb = len(blocks)
    tri_edges, tri_count = (D.upload(a) for a in table())
    up = upper[todo]                                                    # 8 columns
    band = np.unique(up[up < nb])
    band_nbr = upper[band]
    row = np.full(nb + 1, 0, np.int32)        # the zero block owns no vertex: any row will do
    row[band] = np.arange(len(band), dtype=np.int32)

    nbr_dev = D.upload(band_nbr)
    node_first = D.empty(ti.i32, (len(band), B3))
    edges = D.empty(ti.u8, (len(band), B3))
    n_vert = D.empty(ti.i32, len(band))
    count_vertices(rows, nbr_dev, iso, edges, node_first, n_vert)
    n_vert = D.host(n_vert)
    n_points = int(n_vert.sum())
    points = D.empty(ti.f32, n_points, 3)
    vertex_velocity = D.empty(ti.f32, n_points, 3)
    with_velocity = velocity is not None
    vnbr = D.upload(velocity_slot[band_nbr].astype(np.int32)) if with_velocity else nbr_dev
    if not with_velocity:
        vertex_velocity = D.zeros(ti.f32, n_points, 3)
    # each block's first node in metres, in float64 here and rounded once (a grid far from the
    # origin keeps its precision; the kernels need no 64-bit floats, which some Vulkan devices
    # lack); the vertices add their place in the block on the device
    origin = D.upload(blocks[band] * (B * cell), ti.f32)
    place_vertices(rows, nbr_dev, iso, power, D.upload(_exclusive_sum(n_vert)), edges, node_first, origin, cell,
                   points, vnbr, velocity if with_velocity else vertex_velocity, vertex_velocity, with_velocity)

    cases = D.empty(ti.u8, (len(todo), B3))
    n_tri = D.empty(ti.i32, len(todo))
    up_dev = D.upload(up)
    count_triangles(rows, up_dev, iso, tri_count, cases, n_tri)
    n_tri = D.host(n_tri)
    n_faces = int(n_tri.sum())
    faces = D.empty(ti.i32, (n_faces, 3))
    emit_triangles(cases, D.upload(row[up]), tri_edges, tri_count, D.upload(EDGE_CORNER),
                   D.upload(EDGE_AXIS), D.upload(_exclusive_sum(n_tri)), edges, node_first, faces)
    return (D.host(points)[:n_points], D.host(faces)[:n_faces], D.host(vertex_velocity)[:n_points], points,
            faces)


def _exclusive_sum(n: np.ndarray) -> np.ndarray:
    return (np.cumsum(n, dtype=np.int64) - n).astype(np.int32)
