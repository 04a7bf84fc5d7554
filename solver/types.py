"""Taichi types shared by the solver's kernels."""
import taichi as ti

vec3 = ti.math.vec3
vec4 = ti.math.vec4
ivec3 = ti.math.ivec3
ivec2 = ti.math.ivec2
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
V4 = ti.types.ndarray(dtype=vec4, ndim=1)
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
IV2 = ti.types.ndarray(dtype=ivec2, ndim=1)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F4 = ti.types.ndarray(dtype=ti.f32, ndim=4)
D1 = ti.types.ndarray(dtype=ti.f64, ndim=1)
T = ti.template()      # a pass's (ti.func's) arrays: its kernel's own, passed through


@ti.func
def raise_max(a: ti.template(), k: ti.i32, value: ti.f32):
    """a[k] = max(a[k], value), atomically; reading first means that once the maximum is found,
    almost no thread contends for it. A NaN counts as +inf: a comparison with NaN is false and
    a max passes over it, so a particle gone NaN would never show in the maxima while it spread
    to its neighbours for the rest of the frame. The test is on the bits, which fast math
    cannot fold away."""
    v = ti.select((ti.bit_cast(value, ti.u32) & 0x7FFFFFFF) > 0x7F800000, ti.math.inf, value)
    if v > a[k]:
        ti.atomic_max(a[k], v)



# The domain box: its corners, how it bounces (restitution, Coulomb friction) and how far
# particle centres stay from its walls.
Box = ti.types.struct(lo=vec3, hi=vec3, restitution=ti.f32, friction=ti.f32, keep=ti.f32)
# The constants of one WCSPH step: kernel support h, gravity, the Tait exponent, the fill
# lattice's number density and gradient moment, and the surface-tension threshold.
Consts = ti.types.struct(h=ti.f32, gravity=vec3, gamma=ti.f32, lattice=ti.f32, grad_scale=ti.f32,
                         threshold=ti.f32)


# The kernels take Consts and Box packed in one float array, unpacked in the kernel
# (consts_of, box_of): in Taichi's Python launcher a struct argument costs the host about 50 us
# a launch and an array about 10 (measured on the 2-core CPU: two structs 217 us a call, one
# array 113), and on a GPU the WCSPH step is host-bound.
P_H, P_GX, P_GY, P_GZ, P_GAMMA, P_LATTICE, P_GRAD_SCALE, P_THRESHOLD = range(8)
P_LOX, P_LOY, P_LOZ, P_HIX, P_HIY, P_HIZ, P_RESTITUTION, P_FRICTION, P_KEEP = range(8, 17)
P_SIZE = 17


def pack_constants(h, gravity, gamma, lattice, grad_scale, threshold, lo, hi, restitution, friction,
                   keep) -> list[float]:
    """The values of Consts and Box in the order consts_of and box_of read them."""
    values = [h, *gravity, gamma, lattice, grad_scale, threshold, *lo, *hi, restitution, friction, keep]
    assert len(values) == P_SIZE, "pack_constants and the P_* indices disagree"
    return values


@ti.func
def consts_of(p: ti.template()):
    return Consts(h=p[P_H], gravity=vec3(p[P_GX], p[P_GY], p[P_GZ]), gamma=p[P_GAMMA], lattice=p[P_LATTICE],
                  grad_scale=p[P_GRAD_SCALE], threshold=p[P_THRESHOLD])


@ti.func
def box_of(p: ti.template()):
    return Box(lo=vec3(p[P_LOX], p[P_LOY], p[P_LOZ]), hi=vec3(p[P_HIX], p[P_HIY], p[P_HIZ]),
               restitution=p[P_RESTITUTION], friction=p[P_FRICTION], keep=p[P_KEEP])
