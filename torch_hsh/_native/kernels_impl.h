/* Kernel bodies, included twice by kernels.c (T = float / double). */

/* Every loop over the rows j of a block touches element j of its arrays only: no loop-carried
 * dependence, whatever rows of the scratch tables alias; this spares GCC its runtime alias checks
 * (past ten of them it gave up and ran the scalar loop). */
#ifndef IVDEP
#if defined(__GNUC__) && !defined(__clang__)
#define IVDEP _Pragma("GCC ivdep")
#else
#define IVDEP
#endif
#endif

/* Geometry of one block of direction pairs (AoS input), branch-free so that it vectorises.
 * Outputs: t = 2z - 1 of both directions, a, rho, sio, the flag, and for the backward pass
 * the unit vectors, 1/|d| and ds/dz (the horizon-safe derivative). */
static int SUF(geom_block)(int m, const T *wi, const T *wo, T tiny, T eps, T *ti, T *to, T *a, T *rho, T *sio,
                           T *v, T *u /* 6*BS or NULL */, T *inv /* 2*BS */, T *ds /* 2*BS */)
{
    int bad = 0;  /* a non-finite input (or an overflowing |d|^2): the caller runs the full check */
    IVDEP
    for (int j = 0; j < m; ++j) {
        T xi = wi[3 * j], yi = wi[3 * j + 1], zi = wi[3 * j + 2];
        T xo = wo[3 * j], yo = wo[3 * j + 1], zo = wo[3 * j + 2];
        T ni = xi * xi + yi * yi + zi * zi, no = xo * xo + yo * yo + zo * zo;
        bad |= !(ni <= TMAX) | !(no <= TMAX);
        int oki = ni > tiny, oko = no > tiny;
        T ii = oki ? (T)1 / SQRT(ni) : (T)1, io = oko ? (T)1 / SQRT(no) : (T)1;
        xi *= ii; yi *= ii; zi *= ii;
        xo *= io; yo *= io; zo *= io;
        T zpi = zi > 0 ? zi : (T)0, zpo = zo > 0 ? zo : (T)0;
        T si = SQRT(zpi / (1 + zpi)), so = SQRT(zpo / (1 + zpo));
        ti[j] = 2 * zi - 1;
        to[j] = 2 * zo - 1;
        a[j] = xi * xo + yi * yo;
        rho[j] = (xi * xi + yi * yi) * (xo * xo + yo * yo);
        sio[j] = si * so;
        v[j] = (oki && oko && zi >= 0 && zo >= 0) ? (T)1 : (T)0;
        if (u) {
            u[j] = xi; u[BS + j] = yi; u[2 * BS + j] = zi;
            u[3 * BS + j] = xo; u[4 * BS + j] = yo; u[5 * BS + j] = zo;
            inv[j] = ii; inv[BS + j] = io;
            ds[j] = zpi > eps ? (T)0.5 / (si * (1 + zpi) * (1 + zpi)) : (T)0;
            ds[BS + j] = zpo > eps ? (T)0.5 / (so * (1 + zpo) * (1 + zpo)) : (T)0;
        }
    }
    return bad;
}

/* Polar tables (and optionally their z-derivatives) of one block. */
static void SUF(polar_block)(int m, int L, const T *A, const T *B, const int32_t *c1, const int32_t *c2,
                             const T *ti, const T *to, T (*Ri)[BS], T (*Ro)[BS], T (*dRi)[BS], T (*dRo)[BS])
{
    for (int c = 0; c < L; ++c) {
        const T Ac = A[c], Bc = B[c];
        if (c1[c] < 0) {
            IVDEP
            for (int j = 0; j < m; ++j) { Ri[c][j] = Ac; Ro[c][j] = Ac; }
            if (dRi)
                IVDEP
                for (int j = 0; j < m; ++j) { dRi[c][j] = 0; dRo[c][j] = 0; }
            continue;
        }
        const T *restrict ri1 = Ri[c1[c]], *restrict ro1 = Ro[c1[c]];
        T *restrict ric = Ri[c], *restrict roc = Ro[c];
        if (c2[c] < 0) {
            IVDEP
            for (int j = 0; j < m; ++j) { ric[j] = Ac * ti[j] * ri1[j]; roc[j] = Ac * to[j] * ro1[j]; }
        } else {
            const T *restrict ri2 = Ri[c2[c]], *restrict ro2 = Ro[c2[c]];
            IVDEP
            for (int j = 0; j < m; ++j) {
                ric[j] = Ac * ti[j] * ri1[j] - Bc * ri2[j];
                roc[j] = Ac * to[j] * ro1[j] - Bc * ro2[j];
            }
        }
        if (dRi) {  /* d/dz of A t R1 - B R2 with t = 2z - 1 */
            const T *restrict di1 = dRi[c1[c]], *restrict do1 = dRo[c1[c]];
            T *restrict dic = dRi[c], *restrict doc = dRo[c];
            IVDEP
            for (int j = 0; j < m; ++j) {
                dic[j] = Ac * (2 * ri1[j] + ti[j] * di1[j]);
                doc[j] = Ac * (2 * ro1[j] + to[j] * do1[j]);
            }
            if (c2[c] >= 0) {
                const T *restrict di2 = dRi[c2[c]], *restrict do2 = dRo[c2[c]];
                IVDEP
                for (int j = 0; j < m; ++j) { dic[j] -= Bc * di2[j]; doc[j] -= Bc * do2[j]; }
            }
        }
    }
}

/* Forward of one block: out rows (row-major, K per row) from t, a1 = sio a, q1 = sio^2 rho, v. */
static void SUF(core_fwd_block)(int m, const T *ti, const T *to, const T *a1, const T *q1, const T *v, int L,
                                const T *A, const T *B, const int32_t *c1, const int32_t *c2, int P, int K,
                                const int32_t *ka, const int32_t *kb, const int32_t *kq, const T *kc, T *out,
                                T *scratch /* FWD_SCRATCH(L, P, K) values */)
{
    T (*Ri)[BS] = (T(*)[BS])scratch, (*Ro)[BS] = Ri + L, (*G)[BS] = Ro + L, (*tmp)[BS] = G + P + 1;
    SUF(polar_block)(m, L, A, B, c1, c2, ti, to, Ri, Ro, 0, 0);
    IVDEP
    for (int j = 0; j < m; ++j) G[0][j] = v[j];
    if (P >= 1)
        IVDEP
        for (int j = 0; j < m; ++j) G[1][j] = a1[j] * v[j];
    for (int q = 2; q <= P; ++q)
        IVDEP
        for (int j = 0; j < m; ++j) G[q][j] = 2 * a1[j] * G[q - 1][j] - q1[j] * G[q - 2][j];
    for (int k = 0; k < K; ++k) {
        const T *restrict ra = Ri[ka[k]], *restrict rb = Ri[kb[k]], *restrict oa = Ro[ka[k]];
        const T *restrict ob = Ro[kb[k]], *restrict g = G[kq[k]];
        const T ck = kc[k];
        T *restrict t = tmp[k];
        IVDEP
        for (int j = 0; j < m; ++j) t[j] = ck * (ra[j] * ob[j] + rb[j] * oa[j]) * g[j];
    }
    SUF(store_rows)(m, K, tmp, out);
}

/* Backward of one block: gradients with respect to zi, zo, a1, r1 (per row) from gout rows. */
static void SUF(core_bwd_block)(int m, const T *ti, const T *to, const T *a1, const T *q1, const T *v, int L,
                                const T *A, const T *B, const int32_t *c1, const int32_t *c2, int P, int K,
                                const int32_t *ka, const int32_t *kb, const int32_t *kq, const T *kc,
                                const T *gout, int64_t gs0, int64_t gs1, T *restrict gzi, T *restrict gzo, T *restrict ga1, T *restrict gr1,
                                T *scratch /* BWD_SCRATCH(L, P, K) values */)
{
    T (*Ri)[BS] = (T(*)[BS])scratch, (*Ro)[BS] = Ri + L, (*dRi)[BS] = Ro + L, (*dRo)[BS] = dRi + L;
    T (*G)[BS] = dRo + L, (*Ga)[BS] = G + P + 1, (*Gr)[BS] = Ga + P + 1, (*gG)[BS] = Gr + P + 1, (*g)[BS] = gG + P + 1;
    SUF(polar_block)(m, L, A, B, c1, c2, ti, to, Ri, Ro, dRi, dRo);
    SUF(load_rows)(m, K, gout, gs0, gs1, g);
    for (int k = 0; k < K; ++k) {
        const T c = kc[k];
        IVDEP
        for (int j = 0; j < m; ++j) g[k][j] *= c;
    }
    IVDEP
    for (int j = 0; j < m; ++j) { G[0][j] = v[j]; Ga[0][j] = 0; Gr[0][j] = 0; gzi[j] = 0; gzo[j] = 0; }
    for (int q = 0; q <= P; ++q)
        IVDEP
        for (int j = 0; j < m; ++j) gG[q][j] = 0;
    if (P >= 1)
        IVDEP
        for (int j = 0; j < m; ++j) { G[1][j] = a1[j] * v[j]; Ga[1][j] = v[j]; Gr[1][j] = 0; }
    for (int q = 2; q <= P; ++q)
        IVDEP
        for (int j = 0; j < m; ++j) {
            G[q][j] = 2 * a1[j] * G[q - 1][j] - q1[j] * G[q - 2][j];
            Ga[q][j] = 2 * G[q - 1][j] + 2 * a1[j] * Ga[q - 1][j] - q1[j] * Ga[q - 2][j];
            Gr[q][j] = 2 * a1[j] * Gr[q - 1][j] - G[q - 2][j] - q1[j] * Gr[q - 2][j];
        }
    for (int k = 0; k < K; ++k) {
        const int ia = ka[k], ib = kb[k];
        const T *restrict ra = Ri[ia], *restrict rb = Ri[ib], *restrict oa = Ro[ia], *restrict ob = Ro[ib];
        const T *restrict dra = dRi[ia], *restrict drb = dRi[ib], *restrict doa = dRo[ia], *restrict dob = dRo[ib];
        const T *restrict gq = G[kq[k]], *restrict gk = g[k];
        T *restrict acc = gG[kq[k]];
        IVDEP
        for (int j = 0; j < m; ++j) {
            const T w = gk[j], wg = gk[j] * gq[j];
            acc[j] += w * (ra[j] * ob[j] + rb[j] * oa[j]);
            gzi[j] += wg * (dra[j] * ob[j] + drb[j] * oa[j]);
            gzo[j] += wg * (ra[j] * dob[j] + rb[j] * doa[j]);
        }
    }
    IVDEP
    for (int j = 0; j < m; ++j) { ga1[j] = 0; gr1[j] = 0; }
    for (int q = 1; q <= P; ++q)
        IVDEP
        for (int j = 0; j < m; ++j) { ga1[j] += gG[q][j] * Ga[q][j]; gr1[j] += gG[q][j] * Gr[q][j]; }
}

#define CORE_ARGS int L, const T *A, const T *B, const int32_t *c1, const int32_t *c2, int P, int K, \
                  const int32_t *ka, const int32_t *kb, const int32_t *kq, const T *kc
#define CORE_PASS L, A, B, c1, c2, P, K, ka, kb, kq, kc
/* Scratch tables of one block live on the heap (K * BS values reach megabytes at high orders). */
#define FWD_SCRATCH ((size_t)BS * (2 * L + P + 1 + K))
#define BWD_SCRATCH ((size_t)BS * (4 * L + 4 * (P + 1) + K))

/* One block of the five per-row scalars -> t_i, t_o, a1 = sio a, r1 = sio^2 rho and the flag. */
static void SUF(load_scalars)(int m, const T *zi, const T *zo, const T *a, const T *rho, const T *sio,
                              const uint8_t *valid, T *ti, T *to, T *a1, T *q1, T *v)
{
    IVDEP
    for (int j = 0; j < m; ++j) {
        ti[j] = 2 * zi[j] - 1; to[j] = 2 * zo[j] - 1;
        a1[j] = sio[j] * a[j]; q1[j] = sio[j] * sio[j] * rho[j];
        v[j] = valid[j] ? (T)1 : (T)0;
    }
}

int SUF(iso_core_fwd)(int64_t r0, int64_t r1, const T *zi, const T *zo, const T *a, const T *rho, const T *sio,
                       const uint8_t *valid, CORE_ARGS, T *out)
{
    T ti[BS], to[BS], a1[BS], q1[BS], v[BS];
    T *scratch = (T *)malloc(sizeof(T) * FWD_SCRATCH);
    if (!scratch) return 1;  /* out of memory */
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        SUF(load_scalars)(m, zi + b0, zo + b0, a + b0, rho + b0, sio + b0, valid + b0, ti, to, a1, q1, v);
        SUF(core_fwd_block)(m, ti, to, a1, q1, v, CORE_PASS, out + b0 * K, scratch);
    }
    free(scratch);
    return 0;
}

int SUF(iso_core_bwd)(int64_t r0, int64_t r1, const T *zi, const T *zo, const T *a, const T *rho, const T *sio,
                       const uint8_t *valid, CORE_ARGS, const T *gout, int64_t gs0, int64_t gs1, T *gzi, T *gzo, T *ga, T *grho, T *gsio)
{
    T ti[BS], to[BS], a1[BS], q1[BS], v[BS], ga1[BS], gr1[BS];
    T *scratch = (T *)malloc(sizeof(T) * BWD_SCRATCH);
    if (!scratch) return 1;  /* out of memory */
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        SUF(load_scalars)(m, zi + b0, zo + b0, a + b0, rho + b0, sio + b0, valid + b0, ti, to, a1, q1, v);
        SUF(core_bwd_block)(m, ti, to, a1, q1, v, CORE_PASS, gout + b0 * gs0, gs0, gs1, gzi + b0, gzo + b0, ga1, gr1, scratch);
        IVDEP
        for (int j = 0; j < m; ++j) {  /* a1 = sio a, r1 = sio^2 rho */
            int64_t r = b0 + j;
            T s = sio[r];
            ga[r] = ga1[j] * s;
            grho[r] = gr1[j] * s * s;
            gsio[r] = ga1[j] * a[r] + gr1[j] * 2 * s * rho[r];
        }
    }
    free(scratch);
    return 0;
}

int SUF(iso_dirs_fwd)(int64_t r0, int64_t r1, const T *wi, const T *wo, T tiny, T eps, CORE_ARGS, T *out)
{
    T ti[BS], to[BS], a[BS], rho[BS], sio[BS], v[BS];
    int bad = 0;
    T *scratch = (T *)malloc(sizeof(T) * FWD_SCRATCH);
    if (!scratch) return 1;  /* out of memory */
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        bad |= SUF(geom_block)(m, wi + 3 * b0, wo + 3 * b0, tiny, eps, ti, to, a, rho, sio, v, 0, 0, 0);
        IVDEP
        for (int j = 0; j < m; ++j) { T s = sio[j]; a[j] *= s; rho[j] *= s * s; }  /* a1, r1 */
        SUF(core_fwd_block)(m, ti, to, a, rho, v, CORE_PASS, out + b0 * K, scratch);
    }
    free(scratch);
    return bad ? 2 : 0;  /* 2: a non-finite input was seen */
}

int SUF(iso_dirs_bwd)(int64_t r0, int64_t r1, const T *wi, const T *wo, T tiny, T eps, CORE_ARGS, const T *gout,
                      int64_t gs0, int64_t gs1, T *gwi, T *gwo)
{
    T ti[BS], to[BS], a[BS], rho[BS], sio[BS], v[BS], a1[BS], q1[BS], u[6 * BS], inv[2 * BS], ds[2 * BS];
    T gzi[BS], gzo[BS], ga1[BS], gr1[BS];
    T *scratch = (T *)malloc(sizeof(T) * BWD_SCRATCH);
    if (!scratch) return 1;  /* out of memory */
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        (void)SUF(geom_block)(m, wi + 3 * b0, wo + 3 * b0, tiny, eps, ti, to, a, rho, sio, v, u, inv, ds);
        IVDEP
        for (int j = 0; j < m; ++j) { a1[j] = sio[j] * a[j]; q1[j] = sio[j] * sio[j] * rho[j]; }
        SUF(core_bwd_block)(m, ti, to, a1, q1, v, CORE_PASS, gout + b0 * gs0, gs0, gs1, gzi, gzo, ga1, gr1, scratch);
        IVDEP
        for (int j = 0; j < m; ++j) {
            T s = sio[j];
            T ga = ga1[j] * s, grho = gr1[j] * s * s, gsio = ga1[j] * a[j] + gr1[j] * 2 * s * rho[j];
            T xi = u[j], yi = u[BS + j], zi = u[2 * BS + j], xo = u[3 * BS + j], yo = u[4 * BS + j], zo = u[5 * BS + j];
            T pi = xi * xi + yi * yi, po = xo * xo + yo * yo;
            T si = SQRT((zi > 0 ? zi : (T)0) / (1 + (zi > 0 ? zi : (T)0)));
            T so = SQRT((zo > 0 ? zo : (T)0) / (1 + (zo > 0 ? zo : (T)0)));
            T gxi = ga * xo + grho * 2 * xi * po, gyi = ga * yo + grho * 2 * yi * po;
            T gzi_ = gzi[j] + gsio * so * ds[j];
            T gxo = ga * xi + grho * 2 * xo * pi, gyo = ga * yi + grho * 2 * yo * pi;
            T gzo_ = gzo[j] + gsio * si * ds[BS + j];
            /* through u = d / |d|: g_d = (g_u - u (u . g_u)) / |d| (inv = 1 and u = d for zero vectors,
               whose gradients are zero anyway: they are invalid) */
            T pdi = xi * gxi + yi * gyi + zi * gzi_, pdo = xo * gxo + yo * gyo + zo * gzo_;
            T *gi = gwi + 3 * (b0 + j), *go = gwo + 3 * (b0 + j);
            gi[0] = inv[j] * (gxi - xi * pdi); gi[1] = inv[j] * (gyi - yi * pdi); gi[2] = inv[j] * (gzi_ - zi * pdi);
            go[0] = inv[BS + j] * (gxo - xo * pdo); go[1] = inv[BS + j] * (gyo - yo * pdo);
            go[2] = inv[BS + j] * (gzo_ - zo * pdo);
        }
    }
    free(scratch);
    return 0;
}

int SUF(hsh_remap_fwd)(int64_t r0, int64_t r1, const T *d, T tiny, T eps, T *dp, uint8_t *valid)
{
    (void)eps;
    T vb[BS];
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {  /* blocks, so that the float loop vectorises */
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        const T *restrict db = d + 3 * b0;
        T *restrict pb = dp + 3 * b0;
        IVDEP
        for (int j = 0; j < m; ++j) {
            T x = db[3 * j], y = db[3 * j + 1], z = db[3 * j + 2];
            T n2 = x * x + y * y + z * z;
            T inv = n2 > tiny ? (T)1 / SQRT(n2) : (T)1;
            x *= inv; y *= inv; z *= inv;
            T zp = z > 0 ? z : (T)0;
            T s = 2 * SQRT(zp / (1 + zp));
            pb[3 * j] = s * x;
            pb[3 * j + 1] = s * y;
            pb[3 * j + 2] = 2 * zp - 1;
            vb[j] = (n2 > tiny && z >= 0) ? (T)1 : (T)0;
        }
        IVDEP
        for (int j = 0; j < m; ++j) valid[b0 + j] = (uint8_t)(vb[j] != 0);
    }
    return 0;
}

int SUF(hsh_remap_bwd)(int64_t r0, int64_t r1, const T *d, T tiny, T eps, const T *gdp, T *gd)
{
    for (int64_t r = r0; r < r1; ++r) {
        T x = d[3 * r], y = d[3 * r + 1], z = d[3 * r + 2];
        T n2 = x * x + y * y + z * z;
        int ok = n2 > tiny;
        T inv = ok ? (T)1 / SQRT(n2) : (T)1;
        x *= inv; y *= inv; z *= inv;
        T zp = z > 0 ? z : (T)0;
        T sh = SQRT(zp / (1 + zp));
        T ds = zp > eps ? (T)1 / (sh * (1 + zp) * (1 + zp)) : (T)0; /* d(2 sh)/dz, cut near the horizon */
        const T *g = gdp + 3 * r;
        T gx = g[0] * 2 * sh, gy = g[1] * 2 * sh;
        T gz = ds * (g[0] * x + g[1] * y) + (z >= 0 ? 2 * g[2] : (T)0);
        T pd = x * gx + y * gy + z * gz;
        gd[3 * r] = inv * (gx - x * pd);
        gd[3 * r + 1] = inv * (gy - y * pd);
        gd[3 * r + 2] = inv * (gz - z * pd);
    }
    return 0;
}

/* Symmetric pair products (the anisotropic basis from two HSH tables, row-major (N, H)):
 *   out[r, p] = c_p (A[r, j_p] B[r, k_p] + A[r, k_p] B[r, j_p]),  p = 0..Q-1. */
int SUF(pair_fwd)(int64_t r0, int64_t r1, const T *Am, const T *Bm, int H, int Q, const int32_t *pj,
                  const int32_t *pk, const T *pc, T *out)
{
    T *scratch = (T *)malloc(sizeof(T) * (size_t)BS * (2 * H + Q));
    if (!scratch) return 1;
    T (*a)[BS] = (T(*)[BS])scratch, (*b)[BS] = a + H, (*tmp)[BS] = b + H;
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        SUF(load_rows_contig)(m, H, Am + b0 * H, a);
        SUF(load_rows_contig)(m, H, Bm + b0 * H, b);
        for (int p = 0; p < Q; ++p) {
            const T *restrict aj = a[pj[p]], *restrict ak = a[pk[p]], *restrict bj = b[pj[p]], *restrict bk = b[pk[p]];
            const T c = pc[p];
            T *restrict t = tmp[p];
            IVDEP
            for (int j = 0; j < m; ++j) t[j] = c * (aj[j] * bk[j] + ak[j] * bj[j]);
        }
        SUF(store_rows)(m, Q, tmp, out + b0 * (int64_t)Q);
    }
    free(scratch);
    return 0;
}

int SUF(pair_bwd)(int64_t r0, int64_t r1, const T *Am, const T *Bm, int H, int Q, const int32_t *pj,
                  const int32_t *pk, const T *pc, const T *gout, int64_t gs0, int64_t gs1, T *gA, T *gB)
{
    T *scratch = (T *)malloc(sizeof(T) * (size_t)BS * (4 * H + Q));
    if (!scratch) return 1;
    T (*a)[BS] = (T(*)[BS])scratch, (*b)[BS] = a + H, (*ga)[BS] = b + H, (*gb)[BS] = ga + H, (*g)[BS] = gb + H;
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        SUF(load_rows_contig)(m, H, Am + b0 * H, a);
        SUF(load_rows_contig)(m, H, Bm + b0 * H, b);
        for (int h = 0; h < H; ++h)
            IVDEP
            for (int j = 0; j < m; ++j) { ga[h][j] = 0; gb[h][j] = 0; }
        SUF(load_rows)(m, Q, gout + b0 * gs0, gs0, gs1, g);
        for (int p = 0; p < Q; ++p) {
            const T c = pc[p];
            IVDEP
            for (int j = 0; j < m; ++j) g[p][j] *= c;
        }
        for (int p = 0; p < Q; ++p) {
            const int J = pj[p], K = pk[p];
            const T *restrict aj = a[J], *restrict ak = a[K], *restrict bj = b[J], *restrict bk = b[K];
            const T *restrict gp = g[p];
            if (J == K) {
                T *restrict gaj = ga[J], *restrict gbj = gb[J];
                IVDEP
                for (int j = 0; j < m; ++j) { gaj[j] += 2 * gp[j] * bj[j]; gbj[j] += 2 * gp[j] * aj[j]; }
            } else {
                T *restrict gaj = ga[J], *restrict gak = ga[K], *restrict gbj = gb[J], *restrict gbk = gb[K];
                IVDEP
                for (int j = 0; j < m; ++j) {
                    gaj[j] += gp[j] * bk[j]; gak[j] += gp[j] * bj[j];
                    gbk[j] += gp[j] * aj[j]; gbj[j] += gp[j] * ak[j];
                }
            }
        }
        SUF(store_rows)(m, H, ga, gA + b0 * H);
        SUF(store_rows)(m, H, gb, gB + b0 * H);
    }
    free(scratch);
    return 0;
}


/* ---- HSH of one direction set: H_k = ks_k R_{kr_k}(2z - 1) Az_{ka_k}, written straight into (N, K) rows ----
 * R: the polar table (recurrence A, B, c1, c2 as for the isotropic basis, one set), with dR/dz for the backward;
 * Az_m = Re w^m (m = 0..P), Az_{P+m} = Im w^m (m = 1..P), w = s (x + i y), s = sqrt(z / (1 + z)), times the flag;
 * ks_k the azimuthal scale (1, sqrt 2 or (-1)^m sqrt 2). Rows are processed in blocks of BS, feature-major inside
 * a block (every loop runs over the rows and vectorises), then transposed into the output rows (store_rows). */
#define HSH_ARGS int L, const T *A, const T *B, const int32_t *c1, const int32_t *c2, int K, \
                 const int32_t *kr, const int32_t *ka, const T *ks
#define HSH_PASS L, A, B, c1, c2, K, kr, ka, ks
#define HSH_SCRATCH ((size_t)BS * (2 * L + 2 * P + 1 + 2 * K + 8))

/* Unit vectors, flag, t = 2z - 1, s and (bwd) ds/dz (horizon-safe) and 1/|d| of one block of (m, 3) rows. */
static int SUF(hsh_geom)(int m, const T *restrict d, T tiny, T eps, T *restrict x,
        T *restrict y, T *restrict z, T *restrict t, T *restrict s, T *restrict v, T *restrict inv, T *restrict ds)
{
    int bad = 0;  /* a non-finite input (or an overflowing |d|^2): the caller runs the full check */
    IVDEP
    for (int j = 0; j < m; ++j) {
        T xj = d[3 * j], yj = d[3 * j + 1], zj = d[3 * j + 2];
        T n2 = xj * xj + yj * yj + zj * zj;
        bad |= !(n2 <= TMAX);
        int ok = n2 > tiny;
        T ii = ok ? (T)1 / SQRT(n2) : (T)1;
        xj *= ii; yj *= ii; zj *= ii;
        T zp = zj > 0 ? zj : (T)0;
        T sj = SQRT(zp / (1 + zp));
        x[j] = xj; y[j] = yj; z[j] = zj; t[j] = 2 * zj - 1; s[j] = sj;
        v[j] = (ok && zj >= 0) ? (T)1 : (T)0;
        if (inv) {
            inv[j] = ii;
            ds[j] = zp > eps ? (T)0.5 / (sj * (1 + zp) * (1 + zp)) : (T)0;
        }
    }
    return bad;
}

/* Polar table of one set (and its z-derivative where dR is not NULL). */
static void SUF(polar1)(int m, int L, const T *A, const T *B,
        const int32_t *c1, const int32_t *c2, const T *restrict t, T (*R)[BS], T (*dR)[BS])
{
    for (int c = 0; c < L; ++c) {
        const T Ac = A[c], Bc = B[c];
        T *restrict rc = R[c];
        if (c1[c] < 0) {
            IVDEP
            for (int j = 0; j < m; ++j) rc[j] = Ac;
            if (dR)
                IVDEP
                for (int j = 0; j < m; ++j) dR[c][j] = 0;
            continue;
        }
        const T *restrict r1 = R[c1[c]];
        if (c2[c] < 0) {
            IVDEP
            for (int j = 0; j < m; ++j) rc[j] = Ac * t[j] * r1[j];
        } else {
            const T *restrict r2 = R[c2[c]];
            IVDEP
            for (int j = 0; j < m; ++j) rc[j] = Ac * t[j] * r1[j] - Bc * r2[j];
        }
        if (dR) {  /* d/dz of A t R1 - B R2 with t = 2z - 1 */
            const T *restrict d1 = dR[c1[c]];
            T *restrict dc = dR[c];
            IVDEP
            for (int j = 0; j < m; ++j) dc[j] = Ac * (2 * r1[j] + t[j] * d1[j]);
            if (c2[c] >= 0) {
                const T *restrict d2 = dR[c2[c]];
                IVDEP
                for (int j = 0; j < m; ++j) dc[j] -= Bc * d2[j];
            }
        }
    }
}

/* Az rows (see above): Re w^m at 0..P, Im w^m at P+1..2P, with the flag. */
static void SUF(hsh_az)(int m, int P, const T *restrict x, const T *restrict y,
        const T *restrict s, const T *restrict v, T (*Az)[BS])
{
    IVDEP
    for (int j = 0; j < m; ++j) Az[0][j] = v[j];
    if (P < 1) return;
    IVDEP
    for (int j = 0; j < m; ++j) { Az[1][j] = s[j] * x[j] * v[j]; Az[P + 1][j] = s[j] * y[j] * v[j]; }
    for (int q = 2; q <= P; ++q) {
        T *restrict re = Az[q], *restrict im = Az[P + q];
        const T *restrict re1 = Az[q - 1], *restrict im1 = Az[P + q - 1];
        IVDEP
        for (int j = 0; j < m; ++j) {
            T u = s[j] * x[j], w = s[j] * y[j];
            re[j] = re1[j] * u - im1[j] * w;
            im[j] = re1[j] * w + im1[j] * u;
        }
    }
}

static int SUF(hsh_fwd_impl)(int64_t r0, int64_t r1, int P, const T *d, T tiny,
        HSH_ARGS, T *out, T *scratch)
{
    T x[BS], y[BS], z[BS], t[BS], s[BS], v[BS];
    int bad = 0;
    T (*R)[BS] = (T(*)[BS])scratch, (*Az)[BS] = R + L, (*tmp)[BS] = Az + 2 * P + 1;
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        bad |= SUF(hsh_geom)(m, d + 3 * b0, tiny, 0, x, y, z, t, s, v, 0, 0);
        SUF(polar1)(m, L, A, B, c1, c2, t, R, 0);
        SUF(hsh_az)(m, P, x, y, s, v, Az);
        for (int k = 0; k < K; ++k) {
            const T *restrict rk = R[kr[k]], *restrict ak = Az[ka[k]];
            const T c = ks[k];
            T *restrict o = tmp[k];
            IVDEP
            for (int j = 0; j < m; ++j) o[j] = c * rk[j] * ak[j];
        }
        SUF(store_rows)(m, K, tmp, out + b0 * K);
    }
    return bad ? 2 : 0;  /* 2: a non-finite input was seen */
}

/* Backward of one block: gd from the gout rows (strided), see the header comment of hsh_fwd. */
static void SUF(hsh_bwd_block)(int m, int P, const T *d, T tiny, T eps,
        HSH_ARGS, const T *gout, int64_t gs0, int64_t gs1, T *gd, T *scratch)
{
    T x[BS], y[BS], z[BS], t[BS], s[BS], v[BS], inv[BS], ds[BS], gx[BS], gy[BS], gz[BS];
    T (*R)[BS] = (T(*)[BS])scratch, (*dR)[BS] = R + L, (*Az)[BS] = dR + L, (*gA)[BS] = Az + 2 * P + 1;
    T (*g)[BS] = gA + 2 * P + 1;
    (void)SUF(hsh_geom)(m, d, tiny, eps, x, y, z, t, s, v, inv, ds);
    SUF(polar1)(m, L, A, B, c1, c2, t, R, dR);
    SUF(hsh_az)(m, P, x, y, s, v, Az);
    SUF(load_rows)(m, K, gout, gs0, gs1, g);
    for (int a = 0; a <= 2 * P; ++a)
        IVDEP
        for (int j = 0; j < m; ++j) gA[a][j] = 0;
    IVDEP
    for (int j = 0; j < m; ++j) gz[j] = 0;
    for (int k = 0; k < K; ++k) {
        const T *restrict rk = R[kr[k]], *restrict dk = dR[kr[k]], *restrict ak = Az[ka[k]], *restrict gk = g[k];
        T *restrict acc = gA[ka[k]];
        const T c = ks[k];
        IVDEP
        for (int j = 0; j < m; ++j) {
            T w = c * gk[j];
            acc[j] += w * rk[j];
            gz[j] += w * dk[j] * ak[j];
        }
    }
    IVDEP
    for (int j = 0; j < m; ++j) { gx[j] = 0; gy[j] = 0; }
    for (int q = 1; q <= P; ++q) {  /* d w^q = q w^(q-1) (s dx + i s dy + ds (x + i y) dz) */
        const T *restrict re1 = Az[q - 1], *restrict gre = gA[q], *restrict gim = gA[P + q];
        const T *restrict im1 = q > 1 ? Az[P + q - 1] : 0;
        IVDEP
        for (int j = 0; j < m; ++j) {
            T i1 = im1 ? im1[j] : (T)0;
            T a = gre[j] * re1[j] + gim[j] * i1, b = gim[j] * re1[j] - gre[j] * i1;
            gx[j] += q * s[j] * a;
            gy[j] += q * s[j] * b;
            gz[j] += q * ds[j] * (a * x[j] + b * y[j]);
        }
    }
    IVDEP
    for (int j = 0; j < m; ++j) {  /* through u = d / |d| */
        T pd = x[j] * gx[j] + y[j] * gy[j] + z[j] * gz[j];
        gd[3 * j] = inv[j] * (gx[j] - x[j] * pd);
        gd[3 * j + 1] = inv[j] * (gy[j] - y[j] * pd);
        gd[3 * j + 2] = inv[j] * (gz[j] - z[j] * pd);
    }
}

static int SUF(hsh_bwd_impl)(int64_t r0, int64_t r1, int P, const T *d, T tiny,
        T eps, HSH_ARGS, const T *gout, int64_t gs0, int64_t gs1, T *gd, T *scratch)
{
    for (int64_t b0 = r0; b0 < r1; b0 += BS) {
        int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);
        SUF(hsh_bwd_block)(m, P, d + 3 * b0, tiny, eps, HSH_PASS, gout + b0 * gs0, gs0, gs1, gd + 3 * b0, scratch);
    }
    return 0;
}

int SUF(hsh_fwd)(int64_t r0, int64_t r1, int P, const T *d, T tiny, HSH_ARGS, T *out)
{
    T *scratch = (T *)malloc(sizeof(T) * HSH_SCRATCH);
    if (!scratch) return 1;
    int code = SUF(hsh_fwd_impl)(r0, r1, P, d, tiny, HSH_PASS, out, scratch);
    free(scratch);
    return code;
}

int SUF(hsh_bwd)(int64_t r0, int64_t r1, int P, const T *d, T tiny, T eps, HSH_ARGS, const T *gout, int64_t gs0,
                 int64_t gs1, T *gd)
{
    T *scratch = (T *)malloc(sizeof(T) * HSH_SCRATCH);
    if (!scratch) return 1;
    SUF(hsh_bwd_impl)(r0, r1, P, d, tiny, eps, HSH_PASS, gout, gs0, gs1, gd, scratch);
    free(scratch);
    return 0;
}

/* ---- The isotropic basis at low orders as straight-line code (generated: iso_small_fwd / iso_small_bwd) ---- */
#include "kernels_iso_small.h"

/* ---- The same kernels over all rows [0, n) on the OpenMP team (PAR in kernels.c) ---- */
PAR(iso_core_fwd, (const T *zi, const T *zo, const T *a, const T *rho, const T *sio, const uint8_t *valid, CORE_ARGS,
                   T *out),
    (zi, zo, a, rho, sio, valid, CORE_PASS, out))
PAR(iso_core_bwd, (const T *zi, const T *zo, const T *a, const T *rho, const T *sio, const uint8_t *valid, CORE_ARGS,
                   const T *gout, int64_t gs0, int64_t gs1, T *gzi, T *gzo, T *ga, T *grho, T *gsio),
    (zi, zo, a, rho, sio, valid, CORE_PASS, gout, gs0, gs1, gzi, gzo, ga, grho, gsio))
PAR(iso_dirs_fwd, (const T *wi, const T *wo, T tiny, T eps, CORE_ARGS, T *out), (wi, wo, tiny, eps, CORE_PASS, out))
PAR(iso_dirs_bwd, (const T *wi, const T *wo, T tiny, T eps, CORE_ARGS, const T *gout, int64_t gs0, int64_t gs1,
                   T *gwi, T *gwo),
    (wi, wo, tiny, eps, CORE_PASS, gout, gs0, gs1, gwi, gwo))
PAR(iso_small_fwd, (int P, const T *wi, const T *wo, T tiny, T eps, T *out), (P, wi, wo, tiny, eps, out))
PAR(iso_small_bwd, (int P, const T *wi, const T *wo, T tiny, T eps, const T *gout, int64_t gs0, int64_t gs1, T *gwi,
                    T *gwo),
    (P, wi, wo, tiny, eps, gout, gs0, gs1, gwi, gwo))
PAR(hsh_remap_fwd, (const T *d, T tiny, T eps, T *dp, uint8_t *valid), (d, tiny, eps, dp, valid))
PAR(hsh_remap_bwd, (const T *d, T tiny, T eps, const T *gdp, T *gd), (d, tiny, eps, gdp, gd))
PAR(pair_fwd, (const T *Am, const T *Bm, int H, int Q, const int32_t *pj, const int32_t *pk, const T *pc, T *out),
    (Am, Bm, H, Q, pj, pk, pc, out))
PAR(pair_bwd, (const T *Am, const T *Bm, int H, int Q, const int32_t *pj, const int32_t *pk, const T *pc,
               const T *gout, int64_t gs0, int64_t gs1, T *gA, T *gB),
    (Am, Bm, H, Q, pj, pk, pc, gout, gs0, gs1, gA, gB))
PAR(hsh_fwd, (int P, const T *d, T tiny, HSH_ARGS, T *out), (P, d, tiny, HSH_PASS, out))
PAR(hsh_bwd, (int P, const T *d, T tiny, T eps, HSH_ARGS, const T *gout, int64_t gs0, int64_t gs1, T *gd),
    (P, d, tiny, eps, HSH_PASS, gout, gs0, gs1, gd))

#undef HSH_ARGS
#undef HSH_PASS
#undef HSH_SCRATCH

#undef CORE_ARGS
#undef CORE_PASS
#undef FWD_SCRATCH
#undef BWD_SCRATCH
