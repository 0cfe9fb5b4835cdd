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
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define BS 64

#if defined(__AVX512F__)
#include <immintrin.h>
/* In-register transpose of 16 rows of 16 floats. */
static inline void tr16x16(__m512 r[16])
{
    __m512 t[16];
    for (int i = 0; i < 16; i += 2) { t[i] = _mm512_unpacklo_ps(r[i], r[i + 1]); t[i + 1] = _mm512_unpackhi_ps(r[i], r[i + 1]); }
    for (int i = 0; i < 16; i += 4) {
        r[i] = _mm512_shuffle_ps(t[i], t[i + 2], 0x44);
        r[i + 1] = _mm512_shuffle_ps(t[i], t[i + 2], 0xEE);
        r[i + 2] = _mm512_shuffle_ps(t[i + 1], t[i + 3], 0x44);
        r[i + 3] = _mm512_shuffle_ps(t[i + 1], t[i + 3], 0xEE);
    }
    for (int h = 0; h < 16; h += 8)
        for (int i = 0; i < 4; ++i) {
            t[h + i] = _mm512_shuffle_f32x4(r[h + i], r[h + i + 4], 0x88);
            t[h + i + 4] = _mm512_shuffle_f32x4(r[h + i], r[h + i + 4], 0xDD);
        }
    for (int i = 0; i < 8; ++i) {
        r[i] = _mm512_shuffle_f32x4(t[i], t[i + 8], 0x88);
        r[i + 8] = _mm512_shuffle_f32x4(t[i], t[i + 8], 0xDD);
    }
}

/* out[j * K + k] = tmp[k][j] for j < m, k < K (feature-major block -> row-major rows), 16 x 16 tiles. */
static void store_rows_f32(int m, int K, float (*tmp)[BS], float *out)
{
    int j0 = 0;
    for (; j0 + 16 <= m; j0 += 16)
        for (int k0 = 0; k0 < K; k0 += 16) {
            int kk = K - k0 < 16 ? K - k0 : 16;
            __m512 r[16];
            for (int i = 0; i < 16; ++i) r[i] = i < kk ? _mm512_loadu_ps(&tmp[k0 + i][j0]) : _mm512_setzero_ps();
            tr16x16(r);
            __mmask16 mk = (__mmask16)((1u << kk) - 1u);
            for (int i = 0; i < 16; ++i) _mm512_mask_storeu_ps(out + (int64_t)(j0 + i) * K + k0, mk, r[i]);
        }
    for (int j = j0; j < m; ++j)
        for (int k = 0; k < K; ++k) out[(int64_t)j * K + k] = tmp[k][j];
}

/* g[k][j] = rows[j * K + k] (contiguous row-major rows -> feature-major block), 16 x 16 tiles. */
static void load_rows_contig_f32(int m, int K, const float *rows, float (*g)[BS])
{
    int j0 = 0;
    for (; j0 + 16 <= m; j0 += 16)
        for (int k0 = 0; k0 < K; k0 += 16) {
            int kk = K - k0 < 16 ? K - k0 : 16;
            __mmask16 mk = (__mmask16)((1u << kk) - 1u);
            __m512 r[16];
            for (int i = 0; i < 16; ++i) r[i] = _mm512_maskz_loadu_ps(mk, rows + (int64_t)(j0 + i) * K + k0);
            tr16x16(r);
            for (int i = 0; i < kk; ++i) _mm512_storeu_ps(&g[k0 + i][j0], r[i]);
        }
    for (int j = j0; j < m; ++j)
        for (int k = 0; k < K; ++k) g[k][j] = rows[(int64_t)j * K + k];
}
#else
static void load_rows_contig_f32(int m, int K, const float *rows, float (*g)[BS])
{
    for (int k = 0; k < K; ++k)
        for (int j = 0; j < m; ++j) g[k][j] = rows[(int64_t)j * K + k];
}

static void store_rows_f32(int m, int K, float (*tmp)[BS], float *out)
{
    for (int j = 0; j < m; ++j)
        for (int k = 0; k < K; ++k) out[(int64_t)j * K + k] = tmp[k][j];
}
#endif

static void store_rows_f64(int m, int K, double (*tmp)[BS], double *out)
{
    for (int j = 0; j < m; ++j)
        for (int k = 0; k < K; ++k) out[(int64_t)j * K + k] = tmp[k][j];
}

static void load_rows_contig_f64(int m, int K, const double *rows, double (*g)[BS])
{
    for (int k = 0; k < K; ++k)
        for (int j = 0; j < m; ++j) g[k][j] = rows[(int64_t)j * K + k];
}

/* g[k][j] = gout[j * gs0 + k * gs1] for a block of m rows (gout may be strided: an expanded gradient has
 * stride 0, the gradient of a sum is one value everywhere). */
#define LOAD_ROWS(T, SUFX)                                                                                          \
    static void load_rows_##SUFX(int m, int K, const T *gout, int64_t gs0, int64_t gs1, T (*g)[BS])                   \
    {                                                                                                               \
        if (gs1 == 1 && gs0 == K) {                                                                                 \
            load_rows_contig_##SUFX(m, K, gout, g);                                                                 \
        } else if (gs0 == 0) {                                                                                      \
            for (int k = 0; k < K; ++k) {                                                                           \
                const T c = gout[k * gs1];                                                                          \
                for (int j = 0; j < m; ++j) g[k][j] = c;                                                            \
            }                                                                                                       \
        } else {                                                                                                    \
            for (int k = 0; k < K; ++k)                                                                             \
                for (int j = 0; j < m; ++j) g[k][j] = gout[(int64_t)j * gs0 + k * gs1];                             \
        }                                                                                                           \
    }
LOAD_ROWS(float, f32)
LOAD_ROWS(double, f64)
#undef LOAD_ROWS

/* PAR(name, (params), (args)) defines name_par(n, step, nt, params): the row kernel name over [0, n) in
 * ranges of step rows (a multiple of BS, so that the blocks, and the values, do not depend on the split),
 * taken in turn by the nt threads of an OpenMP team. Compiled with -fopenmp, the team is that of the
 * OpenMP runtime already in the process, i.e. torch's own intra-op threads (torch's wheels load
 * libgomp.so.1, and the loader gives this library the same copy), so the kernels and torch's operators
 * share one set of threads instead of competing for the cores. Without OpenMP it runs the ranges in
 * order on the caller's thread. The return code is the bitwise or of the ranges' codes (1: no scratch
 * memory, 2: a non-finite input). */
#define UNPACK(...) __VA_ARGS__
#define PAR(NAME, PARAMS, ARGS)                                                                                     \
    int SUF(NAME##_par)(int64_t n, int64_t step, int nt, UNPACK PARAMS)                                             \
    {                                                                                                               \
        int code = 0;                                                                                               \
        const int64_t chunks = (n + step - 1) / step;                                                               \
        (void)nt;                                                                                                   \
        OMP_FOR                                                                                                     \
        for (int64_t c = 0; c < chunks; ++c) {                                                                      \
            const int64_t r0 = c * step, r1 = r0 + step < n ? r0 + step : n;                                        \
            const int rc = SUF(NAME)(r0, r1, UNPACK ARGS);                                                          \
            code |= rc;                                                                                             \
        }                                                                                                           \
        return code;                                                                                                \
    }
#ifdef _OPENMP
#define OMP_FOR _Pragma("omp parallel for num_threads(nt) schedule(dynamic, 1) reduction(| : code)")
int torch_hsh_openmp(void) { return 1; }
#else
#define OMP_FOR
int torch_hsh_openmp(void) { return 0; }
#endif

#define T float
#define SUF(name) name##_f32
#define SQRT sqrtf
#define TMAX FLT_MAX
#include "kernels_impl.h"
#undef T
#undef SUF
#undef SQRT
#undef TMAX

#define T double
#define SUF(name) name##_f64
#define SQRT sqrt
#define TMAX DBL_MAX
#include "kernels_impl.h"
#undef T
#undef SUF
#undef SQRT
#undef TMAX
