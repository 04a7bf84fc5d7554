"""Taichi types shared by the solver's kernels."""
import taichi as ti

vec3 = ti.math.vec3
ivec3 = ti.math.ivec3
ivec2 = ti.math.ivec2
V3 = ti.types.ndarray(dtype=vec3, ndim=1)
F1 = ti.types.ndarray(dtype=ti.f32, ndim=1)
I1 = ti.types.ndarray(dtype=ti.i32, ndim=1)
F2 = ti.types.ndarray(dtype=ti.f32, ndim=2)
F4 = ti.types.ndarray(dtype=ti.f32, ndim=4)
D1 = ti.types.ndarray(dtype=ti.f64, ndim=1)


@ti.func
def raise_max(a: ti.template(), k: ti.i32, value: ti.f32):
    """a[k] = max(a[k], value), atomically; reading first means that once the maximum is found,
    almost no thread contends for it."""
    if value > a[k]:
        ti.atomic_max(a[k], value)



# The domain box: its corners, how it bounces (restitution, Coulomb friction) and how far
# particle centres stay from its walls.
Box = ti.types.struct(lo=vec3, hi=vec3, restitution=ti.f32, friction=ti.f32, keep=ti.f32)
# The constants of one WCSPH step: kernel support h, gravity, the Tait exponent, the fill
# lattice's number density and gradient moment, and the surface-tension threshold.
Consts = ti.types.struct(h=ti.f32, gravity=vec3, gamma=ti.f32, lattice=ti.f32, grad_scale=ti.f32,
                         threshold=ti.f32)
