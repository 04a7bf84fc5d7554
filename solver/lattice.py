"""The fill's lattices: where the fluid blocks' particles start (NumPy only, no Taichi).

Both lattices hold one particle per (2r)^3, so a particle's mass is the same on either:

- "cubic": the simple cubic lattice of spacing d = 2r, centred in each block (floor(L / d)
  sites a side). WCSPH's wall samples (kernels.ghost_tables) and hydrostatic start are built for
  it. As a start it has one weakness: a simple cubic packing shears by whole rows, and a
  collapsing column keeps its rows as ribs across the outflow's surface, two spacings apart
  (bench/RESULTS.md, twenty-third and twenty-fourth sessions).
- "fcc": face-centred cubic, the densest packing, whose rows do not line up under shear. Its
  planes along each axis are s = d 4^(1/3) / 2 = 1.587 r apart; site (i, j, k) of the plane grid
  is filled where i + j + k is even, and nearest neighbours are s sqrt(2) = 2.245 r apart.
  Blocks that touch or overlap take their sites from one lattice (a cluster), so that oil
  resting on water continues the water's planes and checkerboard, with no gap or crowding at
  the interface: each block takes the sites in it, low face included, high face not. A block
  holds its volume's worth of particles, give or take a plane a side.

  Walls: DFSPH's walls mirror the fluid (solver/dfsph.py). A cluster's planes start half a step
  from a wall it touches, where a wall's mirror images continue the planes (not their
  checkerboard): a wall's layer reads rest density within 0.2 %, an edge's up to 2.8 % over, and
  a corner's site 16 % over (its images in three walls crowd it), so corner sites are left out
  (then their neighbours read 0.92-1.02 of rest). With the outer planes 0.9 r from the walls
  nothing read over rest, but a wall's layer read 6 % under, and a narrow tank's column sank
  0.6 r in its first 50 ms and sloshed. Away from walls a cluster's planes are centred in it.
  Along an axis where the blocks reach both walls (a column in a closed tank) the step is fitted
  to whole planes between them, within 10 % of s: a gap left at one wall would let the fluid
  slump into it. The other axes take the inverse of that stretch, so that a site still stands
  for (2r)^3 (the free surface takes up the difference). The rest state's kernel sum is taken
  over this lattice (params.lattice_density): a stretch of 5 % moves it by 0.08 %.
"""
from __future__ import annotations

import itertools
import math

import numpy as np

FCC_PLANE = 4.0 ** (1.0 / 3.0) / 2.0          # FCC plane step, in cubic spacings d = 2r
_EPS = 1e-9


class Domain:
    """The box the blocks fill: its walls (a face named in `open_faces`, "-x" ... "+z", has
    none) and, for "fcc", the shared lattice: its planes' step and origin along each axis."""

    MAX_FIT = 0.1           # fit the planes to both walls only where that stretches them less

    def __init__(self, domain_min, domain_max, open_faces, spacing: float, lattice: str, blocks):
        self.lo, self.hi = np.asarray(domain_min, float), np.asarray(domain_max, float)
        self.spacing, self.lattice = spacing, lattice
        self.blocks = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in blocks]
        self.wall_lo = [f"-{a}" not in open_faces for a in "xyz"]
        self.wall_hi = [f"+{a}" not in open_faces for a in "xyz"]
        s = FCC_PLANE * spacing if lattice == "fcc" else spacing
        touch_lo = [[self.wall_lo[k] and lo[k] < self.lo[k] + s for k in range(3)] for lo, _ in self.blocks]
        touch_hi = [[self.wall_hi[k] and hi[k] > self.hi[k] - s for k in range(3)] for _, hi in self.blocks]
        both = [any(t[k] for t in touch_lo) and any(t[k] for t in touch_hi) for k in range(3)]
        self.step = self._fitted(s, both) if lattice == "fcc" else np.full(3, s)
        # blocks that touch or overlap share their planes (one cluster); a cluster's planes start
        # half a step from the wall it touches, else they are centred in the cluster's extent,
        # as many as fit it best (a free face may get an outer plane under half a step in)
        self.cluster = _clusters(self.blocks, s)
        self.origins = {}
        for c in set(self.cluster):
            members = [i for i, ci in enumerate(self.cluster) if ci == c]
            lo = np.min([self.blocks[i][0] for i in members], axis=0)
            hi = np.max([self.blocks[i][1] for i in members], axis=0)
            origin = self.lo + 0.5 * self.step
            for k in range(3):
                planes = (hi[k] - lo[k]) / self.step[k]
                if any(touch_lo[i][k] for i in members) or planes >= 1e15:
                    continue
                if any(touch_hi[i][k] for i in members):
                    origin[k] = self.hi[k] - 0.5 * self.step[k]
                else:
                    origin[k] = lo[k] + 0.5 * (hi[k] - lo[k] - (max(round(planes), 1) - 1) * self.step[k])
            self.origins[c] = origin

    def origin_of(self, block: int) -> np.ndarray:
        return self.origins[self.cluster[block]]

    def _fitted(self, s: float, both: list[bool]) -> np.ndarray:
        """Plane steps: along each axis in `both`, the wall-to-wall length over a whole number of
        steps (one fewer or one more than s would give, within MAX_FIT of s); along the others s
        times the inverse of their stretch, shared. Of the choices, the one whose largest
        stretch of any axis (and, with no other axis, of a site's volume) is least."""
        planes = (self.hi - self.lo) / s                 # wall to wall, in steps of s
        choices = []
        for k in range(3):
            fits = []
            if both[k] and planes[k] < 1e15:
                counts = sorted({max(math.floor(planes[k]), 1), max(math.ceil(planes[k]), 1)})
                fits = [planes[k] / m for m in counts if abs(planes[k] / m - 1) <= self.MAX_FIT]
            choices.append(fits or [None])
        best, worst = np.ones(3), math.inf
        for pick in itertools.product(*choices):           # each axis's step over s
            u = np.array([1.0 if x is None else x for x in pick])
            free = [k for k in range(3) if pick[k] is None]
            if free:
                u[free] = (1.0 / np.prod(u[[k for k in range(3) if k not in free]])) ** (1.0 / len(free))
            stretch = max(np.abs(np.log(u)).max(), abs(math.log(np.prod(u))))
            if stretch < worst - 1e-12:
                best, worst = u, stretch
        return s * best

    def planes(self, block: int, k: int) -> tuple[int, int]:
        """[i0, i1): the lattice's plane indices along axis k in block `block`'s [lo, hi), no
        nearer a wall than half a step; at least the plane nearest the middle."""
        lo, hi = self.blocks[block][0][k], self.blocks[block][1][k]
        half = 0.5 * self.step[k] * (1 - 1e-6)
        if self.wall_lo[k]:
            lo = max(lo, self.lo[k] + half)
        if self.wall_hi[k]:
            hi = min(hi, self.hi[k] - half + 2 * _EPS)
        origin = self.origin_of(block)[k]
        x0 = (lo - origin) / self.step[k]
        x1 = (hi - origin) / self.step[k]
        if abs(x1 - x0) > 1e15:
            return 0, int(x1 - x0)
        i0, i1 = math.ceil(x0 - _EPS), math.ceil(x1 - _EPS)
        if i1 <= i0:
            i0 = round(0.5 * (x0 + x1))
            i1 = i0 + 1
        return i0, i1

    def in_corner(self, p: np.ndarray) -> np.ndarray:
        """(N,) bool: sites on the outer planes of three walls at once (a corner of the box)."""
        near = np.zeros(p.shape, bool)
        for k in range(3):
            reach = 0.5 * self.step[k] * (1 + 1e-6)
            near[:, k] = (((p[:, k] - self.lo[k] < reach) & self.wall_lo[k])
                          | ((self.hi[k] - p[:, k] < reach) & self.wall_hi[k]))
        return near.all(1)


def site_count(domain: Domain, block: int) -> float:
    """How many sites `block_sites` gives, without making them (for the pre-flight estimate)."""
    lo, hi = domain.blocks[block]
    if domain.lattice == "cubic":
        return math.prod(_cubic_planes(lo[k], hi[k], domain.spacing)[1] for k in range(3))
    spans = [domain.planes(block, k) for k in range(3)]
    if math.prod(float(i1 - i0) for i0, i1 in spans) > 1e15:
        return math.prod(float(i1 - i0) for i0, i1 in spans) / 2
    n = math.prod(i1 - i0 for i0, i1 in spans)
    # sites with i + j + k even: half of them, give or take one per axis of odd length
    bias = math.prod(((i1 - i0) % 2) * (1 if i0 % 2 == 0 else -1) for i0, i1 in spans)
    ends = np.array(list(itertools.product(*[sorted({i0, i1 - 1}) for i0, i1 in spans])))
    ends = ends[ends.sum(1) % 2 == 0]
    corners = int(domain.in_corner(domain.origin_of(block) + ends * domain.step).sum())
    return max((n + bias) // 2 - corners, 1)


def block_sites(domain: Domain, block: int) -> np.ndarray:
    """(N, 3) float64: the lattice's sites in block `block` (at least one). An fcc site in a
    corner of the box is left out: mirrored in three walls it would read 16 % over rest
    density; without it nothing reads more than 2.8 % over (an edge's sites)."""
    lo, hi = domain.blocks[block]
    if domain.lattice == "cubic":
        axes = [(lambda f, n: f + domain.spacing * np.arange(n))(*_cubic_planes(lo[k], hi[k], domain.spacing))
                for k in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx = [np.arange(*domain.planes(block, k)) for k in range(3)]
    grid = np.stack(np.meshgrid(*idx, indexing="ij"), -1).reshape(-1, 3)
    p = domain.origin_of(block) + grid * domain.step
    keep = (grid.sum(1) % 2 == 0) & ~domain.in_corner(p)
    return p[keep] if keep.any() else p[:1]


def _clusters(blocks, gap: float) -> list[int]:
    """Each block's cluster: blocks whose boxes touch or overlap (within `gap`) are joined."""
    parent = list(range(len(blocks)))

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, (lo_a, hi_a) in enumerate(blocks):
        for b in range(a):
            lo_b, hi_b = blocks[b]
            if np.all(np.maximum(lo_a, lo_b) <= np.minimum(hi_a, hi_b) + gap):
                parent[root(a)] = root(b)
    return [root(i) for i in range(len(blocks))]


def _cubic_planes(lo: float, hi: float, spacing: float) -> tuple[float, int]:
    """(first, count): floor(L / d) planes a side, at least one, centred in [lo, hi]."""
    length = hi - lo
    n = max(math.floor(length / spacing + 1e-6), 1) if length / spacing < 1e15 else length / spacing
    return lo + 0.5 * (length - (n - 1) * spacing), n


def sites_near(steps, lattice: str, reach: float) -> np.ndarray:
    """(M, 3): the unbounded lattice's sites within `reach` of the site at the origin, itself
    included (for the rest state's kernel sums): "cubic" of spacing `steps`, or "fcc" with plane
    steps `steps` (one number, or one per axis)."""
    steps = np.broadcast_to(np.asarray(steps, float), (3,))
    n = int(math.ceil(reach / steps.min())) + 1
    ax = np.arange(-n, n + 1)
    idx = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    if lattice == "fcc":
        idx = idx[idx.sum(1) % 2 == 0]
    p = idx * steps
    return p[np.linalg.norm(p, axis=1) <= reach]
