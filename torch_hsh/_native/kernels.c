/* Fused CPU kernels of torch_hsh (loaded by torch_hsh/_native/__init__.py).
 *
 * Plain C99, no Python or torch headers: the shared library is compiled at first
 * use with the system C compiler and called through ctypes on raw, contiguous
 * buffers. Every function works on a row range [r0, r1), so that the caller can
 * split the rows over threads (ctypes releases the GIL). The bodies are written
 * once in kernels_impl.h and instantiated here for float (_f32) and double (_f64).
 *
 * The isotropic Helmholtz basis from five per-row scalars
 *   zi, zo (cosines), a = sin_i sin_o cos(dphi), rho = sin_i^2 sin_o^2, sio = s_i s_o
 * and a validity flag v:
 *   out_k = c_k (R_a(zi) R_b(zo) + R_b(zi) R_a(zo)) G_q,
 *   G_0 = v, G_1 = a1 v, G_{q+1} = 2 a1 G_q - r1 G_{q-1},   a1 = sio a, r1 = sio^2 rho,
 * with R_c the normalised shifted Legendre table (column c of the block layout of
 * torch_hsh.basis._polar_consts) from its three-term recurrence in t = 2z - 1:
 *   R_c = A_c (c1 < 0, the diagonal n = m),   R_c = A_c t R_c1 - B_c R_c2 (no second term if c2 < 0).
 * The rows are processed in blocks of BS that live in the L1 cache; inside a block
 * every loop runs over the rows, so the compiler vectorises it.
 *
 *   iso_core_{fwd,bwd}: from the five scalars (gradients with respect to them);
 *   iso_dirs_{fwd,bwd}: from two (N, 3) direction arrays (normalised here; zero
 *     vectors and z < 0 are invalid), the geometry fused into the same blocks, with
 *     the horizon-safe derivative of s = sqrt(z / (1 + z)) (cut to zero for z <= eps);
 *   hsh_remap_{fwd,bwd}: d -> d' = (s x, s y, 2 z - 1), s = 2 sqrt(z / (1 + z)) of the
 *     unit direction (the map that turns real spherical harmonics into HSH), and the flag.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define BS 64

#define T float
#define SUF(name) name##_f32
#define SQRT sqrtf
#include "kernels_impl.h"
#undef T
#undef SUF
#undef SQRT

#define T double
#define SUF(name) name##_f64
#define SQRT sqrt
#include "kernels_impl.h"
#undef T
#undef SUF
#undef SQRT
