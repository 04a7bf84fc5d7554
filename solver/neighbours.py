"""Neighbour search: particles counting-sorted by grid cell, and Verlet lists.

Cells are (h + skin) / div wide (div: CELL_DIV on a GPU, 1 on the CPU). The sort (count, scan,
scatter, gather) keeps each cell's particles contiguous in memory; a particle's Verlet list holds
every other particle within h + skin of it at the reference positions the lists were built at.
On the CPU the particles of a cell are listed GROUP at a time: each candidate is read once for
the group (list_pass).
"""
import taichi as ti

from .types import D1, I1, T, V3, ivec2, ivec3, raise_max, vec3

SCAN_BLOCK = 256
# On a GPU, cells are (h + skin) / CELL_DIV wide; a particle's list neighbours lie within CELL_DIV
# cells each way. With CELL_DIV = 2 the 5 x 5 x 5 cells searched cover 42% less volume than 3 x 3 x 3
# cells of size h, so fewer candidates are tested; each row of 5 cells along x is contiguous in memory.
CELL_DIV = 2
# On the CPU: cells h + skin wide, and a cell's particles listed GROUP at a time against the 3 x 3
# rows of 3 cells around it (grouped_list_pass). A candidate is then loaded once for GROUP
# distance tests, which LLVM packs into one vector operation at 4, and a particle pays for
# 9 / GROUP rows (each row's loop ends in a mispredicted exit) instead of 25, though it tests 1.7
# times the candidates. The list pass alone on bench/solver.py's dam break at 0.15 s (1.45 M
# pairs, medians of 40): 12.1-12.6 ms as CELL_DIV = 2 lists, 5.3-6.3 ms grouped by 4, 14-17 ms by
# 3, 5 or 6 (registers spilled, nothing packed); and the sort's passes over the cells run over 8
# times fewer cells (bench/RESULTS.md, fortieth session). On a 2-core AMD EPYC (Zen 4) the grouped
# pass was the slower, 18-20 ms against 13.5-16.5, until the list step was a constant there
# (list_step): then 6.5-8.1 ms against 14.6-15.2 (forty-first session).
GROUP = 4
FAR = 1e10     # m: where a group's missing members are tested from
# Verlet-list skin, in units of h: lists hold pairs within h (1 + SKIN) and last until a particle
# has moved SKIN h / 2 from where they were built. Measured on the 50k dam break (bench/solver.py,
# 0.5 s): 0.15 rebuilds too often, 0.25 lists too many pairs; 0.2 was fastest.
SKIN = 0.2


@ti.func
def list_step(lay, rows: ti.template()):
    """The step between a particle's list entries i * lay.x + m * lay.y (SPHSolver.lay): with
    `rows` (each particle's list a row: the CPU's layout) the constant 1, so that the passes'
    loops over a list compile with the entries side by side; else lay.y. With lay.y read at run
    time, LLVM vectorised the passes' loops with each entry's address computed apart: 1 known to
    the compiler made DFSPH's passes 3-10 % faster and the grouped list pass 2.5 times (2-core
    AMD EPYC; bench/RESULTS.md, forty-first session)."""
    step = lay.y
    if ti.static(rows):
        step = 1
    return step


@ti.func
def cell_of(p, origin, inv_cell: ti.f32, dims):
    c = ti.cast(ti.floor((p - origin) * inv_cell), ti.i32)
    return ti.math.clamp(c, 0, dims - 1)


@ti.func
def flat(c, dims) -> ti.i32:
    return c.x + dims.x * (c.y + dims.y * c.z)


# The sort's passes: each a kernel of its own (SPHSolver's separate launches) and a step of
# k_rebuild (all in one launch).


@ti.func
def clear_pass(a: T, b: T):
    for i in a:
        a[i] = 0
        b[i] = 0


@ti.func
def count_pass(position: T, cell: T, count: T, origin: T, inv_cell: ti.f32, dims: T):
    for i in position:
        c = flat(cell_of(position[i], origin, inv_cell, dims), dims)
        cell[i] = c
        ti.atomic_add(count[c], 1)


@ti.func
def scan_blocks_pass(count: T, start: T, block_sum: T, n: ti.i32):
    """Exclusive scan inside blocks of SCAN_BLOCK cells, blocks in parallel (count and start
    may be one array: each entry is read before it is written)."""
    for b in range((n + SCAN_BLOCK - 1) // SCAN_BLOCK):
        s = 0
        for k in range(SCAN_BLOCK):
            c = b * SCAN_BLOCK + k
            if c < n:
                v = count[c]
                start[c] = s
                s += v
        block_sum[b] = s


@ti.func
def scan_serial_pass(a: T, n: ti.i32):
    """Exclusive scan of n values on one thread."""
    for _ in range(1):
        s = 0
        for c in range(n):
            v = a[c]
            a[c] = s
            s += v


@ti.func
def scan_add_pass(start: T, block_sum: T, n: ti.i32):
    for c in range(n):
        start[c] += block_sum[c // SCAN_BLOCK]


@ti.func
def scatter_pass(cell: T, start: T, fill: T, order: T):
    """order[start[c] ...]: each cell's particles, in the order the threads' atomic adds happen
    to come (sort_runs_pass then fixes it)."""
    for i in cell:
        c = cell[i]
        order[start[c] + ti.atomic_add(fill[c], 1)] = i


@ti.func
def sort_run(a: T, s0, n):
    """a[s0 : s0 + n] in increasing order, in place (insertion sort, for the short runs of a
    counting sort's cells)."""
    for k in range(1, n):
        x = a[s0 + k]
        b = k - 1
        while b >= 0:
            if a[s0 + b] <= x:
                break
            a[s0 + b + 1] = a[s0 + b]
            b -= 1
        a[s0 + b + 1] = x


@ti.func
def sort_runs_pass(start: T, count: T, order: T):
    """Each cell's run of `order` in increasing index: the particles of a cell keep their
    previous order, whatever order the scatter's atomics came in, so every later sum adds in
    the same order on every run, with any number of threads. (Without it two 2-thread runs of
    the example parted at frame 8 and were centimetres apart by frame 10.)"""
    for c in count:
        sort_run(order, start[c], count[c])


@ti.func
def gather_pass(order: T, position: T, ref: T, velocity: T, acceleration: T, fluid: T, id: T,
                position_o: T, ref_o: T, velocity_o: T, acceleration_o: T, fluid_o: T, id_o: T):
    """Permute the particle arrays into sorted order: out[s] = in[order[s]]."""
    for s in order:
        i = order[s]
        position_o[s] = position[i]
        ref_o[s] = ref[i]
        velocity_o[s] = velocity[i]
        acceleration_o[s] = acceleration[i]
        fluid_o[s] = fluid[i]
        id_o[s] = id[i]


@ti.kernel
def k_clear2(a: I1, b: I1):
    clear_pass(a, b)


@ti.kernel
def k_count(position: V3, cell: I1, count: I1, origin: vec3, inv_cell: ti.f32, dims: ivec3):
    count_pass(position, cell, count, origin, inv_cell, dims)


@ti.kernel
def k_scan_blocks(count: I1, start: I1, block_sum: I1, n: ti.i32):
    scan_blocks_pass(count, start, block_sum, n)


@ti.kernel
def k_scan_serial(a: I1, n: ti.i32):
    scan_serial_pass(a, n)


@ti.kernel
def k_scan_add(start: I1, block_sum: I1, n: ti.i32):
    scan_add_pass(start, block_sum, n)


def exclusive_scan(count, start, n: int, buffer) -> None:
    """start[i] = count[0] + ... + count[i - 1] for the first n entries: runs of SCAN_BLOCK in
    parallel, then their totals scanned the same way (recursively: a single thread over 17k
    totals took 2.3 ms a step at 1M particles on a GPU), then added back. buffer(level, size)
    gives an int32 array of at least `size` for each level's totals."""
    if n == 0:
        return
    nb = (n + SCAN_BLOCK - 1) // SCAN_BLOCK
    sums = buffer(0, nb)
    k_scan_blocks(count, start, sums, n)
    if nb <= SCAN_BLOCK:
        k_scan_serial(sums, nb)
    else:
        scanned = buffer(1, nb)
        exclusive_scan(sums, scanned, nb, lambda level, size: buffer(level + 2, size))
        sums = scanned
    k_scan_add(start, sums, n)


@ti.kernel
def k_scatter(cell: I1, start: I1, count: I1, fill: I1, order: I1):
    scatter_pass(cell, start, fill, order)
    sort_runs_pass(start, count, order)


@ti.kernel
def k_gather(order: I1, position: V3, ref: V3, velocity: V3, acceleration: V3, fluid: I1, id: I1,
             position_o: V3, ref_o: V3, velocity_o: V3, acceleration_o: V3, fluid_o: I1, id_o: I1):
    gather_pass(order, position, ref, velocity, acceleration, fluid, id,
                position_o, ref_o, velocity_o, acceleration_o, fluid_o, id_o)


@ti.kernel
def k_neighbours(ref: V3, verlet: I1, verlet_count: I1, cap: ti.i32, lay: ivec2, rows: ti.template(),
                 reach: ti.f32, start: I1, count: I1, origin: vec3, inv_cell: ti.f32, dims: ivec3, longest: D1,
                 at: ti.i32, group: ti.template()):
    list_pass(ref, verlet, verlet_count, cap, lay, rows, reach, start, count, origin, inv_cell, dims, longest, at,
              group)


@ti.func
def list_pass(ref: ti.template(), verlet: ti.template(), verlet_count: ti.template(), cap: ti.i32,
              lay: ti.template(), rows: ti.template(), reach: ti.f32, start: ti.template(), count: ti.template(),
              origin: ti.template(), inv_cell: ti.f32, dims: ti.template(), longest: ti.template(), at: ti.i32,
              group: ti.template()):
    """Verlet lists: every j != i within `reach` (= h + skin) of i, at the reference positions,
    in grid order, entry m at verlet[i * lay.x + m * lay.y] (see SPHSolver.lay; list_step). A
    particle with more than `cap` raises longest[at] to its count (longest[at] starts at 0 here),
    and the lists are built again larger; with `rows` longest[at + 1] (clock.LONGEST) ends as the
    longest list built, for the density pass to copy the pairs within h into rows no wider
    (SPHSolver.near_lay; interleaved lists, a GPU's, have no rows to narrow).
    The candidate loop has no branch: in a disordered fluid, whether a candidate is a neighbour is
    a coin toss that a branch predictor keeps losing. group > 1 (cells reach wide):
    grouped_list_pass, the same lists for the same sort."""
    longest[at], longest[at + 1] = 0.0, 0.0
    if ti.static(group > 1):
        grouped_list_pass(ref, verlet, verlet_count, cap, lay, rows, reach, start, count, origin, inv_cell, dims,
                          longest, at, group)
    else:
        cell_list_pass(ref, verlet, verlet_count, cap, lay, rows, reach, start, count, origin, inv_cell, dims,
                       longest, at)


@ti.func
def cell_list_pass(ref: ti.template(), verlet: ti.template(), verlet_count: ti.template(), cap: ti.i32,
                   lay: ti.template(), rows: ti.template(), reach: ti.f32, start: ti.template(), count: ti.template(),
                   origin: ti.template(), inv_cell: ti.f32, dims: ti.template(), longest: ti.template(), at: ti.i32):
    """list_pass a particle at a time, over the CELL_DIV-wide cells' 5 x 5 rows."""
    for i in ref:
        xi = ref[i]
        ci = cell_of(xi, origin, inv_cell, dims)
        m = 0
        base = i * lay.x
        step = list_step(lay, rows)
        for dz, dy in ti.ndrange((-CELL_DIV, CELL_DIV + 1), (-CELL_DIV, CELL_DIV + 1)):
            cy, cz = ci.y + dy, ci.z + dz
            if 0 <= cy < dims.y and 0 <= cz < dims.z:
                # the cells of a row along x are contiguous: one loop over their particles
                x0 = ti.max(ci.x - CELL_DIV, 0)
                x1 = ti.min(ci.x + CELL_DIV, dims.x - 1)
                c0 = flat(ivec3(x0, cy, cz), dims)
                c1 = flat(ivec3(x1, cy, cz), dims)
                for j in range(start[c0], start[c1] + count[c1]):
                    r2 = (xi - ref[j]).norm_sqr()
                    verlet[base + ti.min(m, cap - 1) * step] = j
                    m += ti.select((r2 < reach * reach) & (j != i), 1, 0)
        verlet_count[i] = ti.min(m, cap)
        if m > cap:
            ti.atomic_max(longest[at], ti.cast(m, ti.f64))
        if ti.static(rows):       # (read only for rows: SPHSolver.build_lists)
            raise_max(longest, at + 1, ti.cast(ti.min(m, cap), ti.f32))


@ti.func
def grouped_list_pass(ref: ti.template(), verlet: ti.template(), verlet_count: ti.template(), cap: ti.i32,
                      lay: ti.template(), rows: ti.template(), reach: ti.f32, start: ti.template(),
                      count: ti.template(), origin: ti.template(), inv_cell: ti.f32, dims: ti.template(),
                      longest: ti.template(), at: ti.i32, group: ti.template()):
    """list_pass over cells `reach` wide, `group` particles of a cell at a time: the thread of a
    cell's particle k * group lists it and the next group - 1 of its cell against the 3 x 3 rows
    of 3 cells around their cell, each candidate read once and tested for each (each list holds
    the entries, in the order, that the rows would give a particle alone). Branch-free as the
    candidate loop is: where the cell has fewer members left, the missing ones are tested from
    FAR away and write into the leader's last slot. That slot is every list's spill slot (a
    member's entries past it land there too), so a list holds at most cap - 1 entries, and one
    with more raises longest[at] to its count."""
    for i in ref:
        ci = cell_of(ref[i], origin, inv_cell, dims)
        c = flat(ci, dims)
        s0 = start[c]
        if (i - s0) % group == 0:
            step = list_step(lay, rows)
            g = ti.min(group, s0 + count[c] - i)
            xs = ti.Matrix.zero(ti.f32, group, 3)
            m = ti.Vector.zero(ti.i32, group)         # each member's neighbours so far
            addr = ti.Vector.zero(ti.i32, group)      # where its next entry goes
            end = ti.Vector.zero(ti.i32, group)       # its list's last slot, where it overflows into
            for p in ti.static(range(group)):
                xp = vec3(FAR)                        # no member: never within reach, and writes
                k = i                                 # only into the leader's last slot
                if p < g:
                    xp, k = ref[i + p], i + p
                for d in ti.static(range(3)):
                    xs[p, d] = xp[d]
                end[p] = k * lay.x + (cap - 1) * step
                addr[p] = ti.select(p < g, k * lay.x, end[p])
            for dz, dy in ti.ndrange((-1, 2), (-1, 2)):
                cy, cz = ci.y + dy, ci.z + dz
                if 0 <= cy < dims.y and 0 <= cz < dims.z:
                    c0 = flat(ivec3(ti.max(ci.x - 1, 0), cy, cz), dims)
                    c1 = flat(ivec3(ti.min(ci.x + 1, dims.x - 1), cy, cz), dims)
                    for j in range(start[c0], start[c1] + count[c1]):
                        xj = ref[j]
                        for p in ti.static(range(group)):
                            r2 = (xs[p, 0] - xj[0]) ** 2 + (xs[p, 1] - xj[1]) ** 2 + (xs[p, 2] - xj[2]) ** 2
                            verlet[addr[p]] = j
                            inside = (r2 < reach * reach) & (j != i + p)
                            m[p] += ti.select(inside, 1, 0)
                            addr[p] = ti.min(addr[p] + ti.select(inside, step, 0), end[p])
            for p in ti.static(range(group)):
                if p < g:
                    verlet_count[i + p] = ti.min(m[p], cap - 1)
                    if m[p] > cap - 1:
                        ti.atomic_max(longest[at], ti.cast(m[p], ti.f64))
                    if ti.static(rows):
                        raise_max(longest, at + 1, ti.cast(ti.min(m[p], cap - 1), ti.f32))


# --------------------------------------------------------------- the whole rebuild, one launch
@ti.kernel
def k_rebuild(position: V3, ref: V3, velocity: V3, acceleration: V3, fluid: I1, id: I1,
              position_o: V3, ref_o: V3, velocity_o: V3, acceleration_o: V3, fluid_o: I1, id_o: I1,
              cell: I1, count: I1, fill: I1, start: I1, order: I1, sums: I1, sums2: I1,
              verlet: I1, verlet_count: I1, cap: ti.i32, lay: ivec2, rows: ti.template(), reach: ti.f32,
              origin: vec3, inv_cell: ti.f32, dims: ivec3, longest: D1, at: ti.i32, n: ti.i32, nb: ti.i32,
              nb2: ti.i32, from_position: ti.template(), group: ti.template()):
    """The sort and the lists of SPHSolver.build_lists in one launch (its loops run in order on
    the device, as the ten launches they replace did; see wcsph.k_step for why): the counting
    sort into the *_o arrays, then k_neighbours' lists at the sorted reference positions. With
    `from_position` the reference positions are the current ones (ref = position, then sort).
    The cell scan has two levels of SCAN_BLOCK-cell runs and a serial scan of the top level's
    totals (exact: integers); each cell's particles keep their previous order (sort_runs_pass).
    n, nb, nb2: the lengths of count, sums and sums2, as arguments: a loop bound computed from an
    array's shape inside the kernel does not compile for Vulkan (SPIR-V) in Taichi 1.7."""
    source = ti.static(position if from_position else ref)      # the reference positions
    clear_pass(count, fill)
    count_pass(source, cell, count, origin, inv_cell, dims)
    scan_blocks_pass(count, start, sums, n)          # runs of cells
    scan_blocks_pass(sums, sums, sums2, nb)          # runs of the runs' totals, in place
    scan_serial_pass(sums2, nb2)
    scan_add_pass(sums, sums2, nb)
    scan_add_pass(start, sums, n)
    scatter_pass(cell, start, fill, order)
    sort_runs_pass(start, count, order)
    gather_pass(order, position, source, velocity, acceleration, fluid, id,
                position_o, ref_o, velocity_o, acceleration_o, fluid_o, id_o)
    list_pass(ref_o, verlet, verlet_count, cap, lay, rows, reach, start, count, origin, inv_cell, dims, longest, at,
              group)


@ti.kernel
def k_moved_beyond(position: V3, ref: V3, limit: ti.f32, flag: I1):
    """flag[0] = 1 if some particle is `limit` or more from its reference position: a plain
    store (every writer writes 1), where a maximum over all particles was one atomic per thread
    and, on a GPU, cost as much as the density pass at 1M particles."""
    for i in position:
        if (position[i] - ref[i]).norm() >= limit:
            flag[0] = 1



@ti.kernel
def k_follow(order: I1, src: ti.types.ndarray(ndim=1), dst: ti.types.ndarray(ndim=1)):
    """dst[s] = src[order[s]]: a per-particle array (of any element type: Taichi compiles one
    kernel per type) follows the sort."""
    for s in order:
        dst[s] = src[order[s]]
