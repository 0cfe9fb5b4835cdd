"""Generator of ``torch_hsh/_native/kernels_iso_small.h``: the isotropic Helmholtz basis of two direction sets at low orders,
as straight-line code with the recurrence and output tables written in as constants.

At the orders that BRDF work uses (P = 1..3) the general kernel of ``kernels_impl.h`` spends its time in
short loops over the rows of a block that each load two or three tables and store one (load/store bound):
at P = 2 it ran 15-19x the time of an elementwise multiply that writes the same output. With the tables
known at compile time every polar value, azimuthal factor and output of one row is a register, and the
compiler vectorises one loop over the rows that does all of it.

The tables are those of :func:`torch_hsh.kernel._native_iso_spec`, the same ones that the general kernel
receives at run time, so the two evaluate the same recurrences in the same order (the values agree to
rounding; a test compares them). The generated file is committed; a test checks that it is what this
script generates, and ``python tools/generate_iso_kernels.py`` rewrites it (``--check``: only compare).
The orders are ``torch_hsh._native.ISO_SMALL_ORDERS``.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import List

from torch_hsh._native import ISO_SMALL_ORDERS as ORDERS  # noqa: E402
from torch_hsh.kernel import _native_iso_spec  # noqa: E402

TARGET = Path(__file__).resolve().parent.parent / "torch_hsh" / "_native" / "kernels_iso_small.h"


def _c(x: float) -> str:
    """An exact C literal of ``x`` (hexadecimal float), cast to the kernel's type."""
    return f"(T){float(x).hex()}"


def _order_source(P: int) -> str:
    L, A, B, c1, c2, ka, kb, kq, kc = _native_iso_spec(P)
    K = len(ka)

    def polar(side: str, deriv: bool) -> List[str]:
        lines = []
        for c in range(L):
            if c1[c] < 0:
                lines.append(f"const T R{side}{c} = {_c(A[c])};")
                continue
            expr = f"{_c(A[c])} * t{side} * R{side}{c1[c]}"
            if c2[c] >= 0:
                expr += f" - {_c(B[c])} * R{side}{c2[c]}"
            lines.append(f"const T R{side}{c} = {expr};")
            if deriv:  # d/dz of A t R1 - B R2 with t = 2z - 1
                d1 = f"D{side}{c1[c]}" if c1[c1[c]] >= 0 else None
                dexpr = f"{_c(A[c])} * (2 * R{side}{c1[c]}" + (f" + t{side} * {d1})" if d1 else ")")
                if c2[c] >= 0 and c1[c2[c]] >= 0:
                    dexpr += f" - {_c(B[c])} * D{side}{c2[c]}"
                lines.append(f"const T D{side}{c} = {dexpr};")
        return lines

    fwd = [f"/* ---- P = {P}: L = {L} polar columns, K = {K} outputs ---- */",
           f"static int SUF(iso{P}_fwd)(int64_t r0, int64_t r1, const T *wi, const T *wo, T tiny, T *out)",
           "{",
           f"    T tmp[{K}][BS];",
           "    int bad = 0;",
           "    for (int64_t b0 = r0; b0 < r1; b0 += BS) {",
           "        const int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);",
           "        const T *wib = wi + 3 * b0, *wob = wo + 3 * b0;",
           "        IVDEP",
           "        for (int j = 0; j < m; ++j) {",
           "            ISO_SMALL_GEOM_FWD",
           "            const T a1 = sio * a, q1 = sio2 * rho;",
           "            (void)q1;"]
    body = polar("i", False) + polar("o", False)
    body += ["const T G0 = v;"]
    if P >= 1:
        body += ["const T G1 = a1 * v;"]
    for q in range(2, P + 1):
        body += [f"const T G{q} = 2 * a1 * G{q - 1} - q1 * G{q - 2};"]
    for k in range(K):
        a, b = ka[k], kb[k]
        body += [f"tmp[{k}][j] = {_c(kc[k])} * (Ri{a} * Ro{b} + Ri{b} * Ro{a}) * G{kq[k]};"]
    fwd += ["            " + ln for ln in body]
    fwd += ["        }",
            f"        SUF(store_rows)(m, {K}, tmp, out + b0 * {K});",
            "    }",
            "    return bad ? 2 : 0;",
            "}",
            ""]

    bwd = [f"static int SUF(iso{P}_bwd)(int64_t r0, int64_t r1, const T *wi, const T *wo, T tiny, T eps, const T *gout,",
           "                            int64_t gs0, int64_t gs1, T *gwi, T *gwo)",
           "{",
           f"    T g[{K}][BS];",
           "    int bad = 0; /* set by ISO_SMALL_GEOM; the forward reports non-finite input */",
           "    for (int64_t b0 = r0; b0 < r1; b0 += BS) {",
           "        const int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);",
           "        const T *wib = wi + 3 * b0, *wob = wo + 3 * b0;",
           f"        SUF(load_rows)(m, {K}, gout + b0 * gs0, gs0, gs1, g);",
           "        IVDEP",
           "        for (int j = 0; j < m; ++j) {",
           "            ISO_SMALL_GEOM",
           "            ISO_SMALL_GEOM_BWD",
           "            const T a1 = sio * a, q1 = sio * sio * rho;",
           "            (void)q1;"]
    body = polar("i", True) + polar("o", True)
    body += ["const T G0 = v;"]
    if P >= 1:
        body += ["const T G1 = a1 * v, Ga1 = v;"]
    for q in range(2, P + 1):  # G and its derivatives with respect to a1 (Ga) and q1 (Gr)
        ga_prev2 = f" - q1 * Ga{q - 2}" if q - 2 >= 1 else ""
        ga = f"2 * G{q - 1} + 2 * a1 * Ga{q - 1}{ga_prev2}"
        gr_terms = []
        if q - 1 >= 2:
            gr_terms.append(f"2 * a1 * Gr{q - 1}")
        gr_terms.append(f"- G{q - 2}")
        if q - 2 >= 2:
            gr_terms.append(f"- q1 * Gr{q - 2}")
        gr = " ".join(gr_terms).lstrip()
        body += [f"const T G{q} = 2 * a1 * G{q - 1} - q1 * G{q - 2};",
                 f"const T Ga{q} = {ga};",
                 f"const T Gr{q} = {gr if not gr.startswith('- ') else '-' + gr[2:]};"]
    body += [f"T gG{q} = 0;" for q in range(1, P + 1)]
    body += ["T gzi = 0, gzo = 0;"]
    for k in range(K):
        a, b, q = ka[k], kb[k], kq[k]
        # d/dz_i and d/dz_o of R_a(zi) R_b(zo) + R_b(zi) R_a(zo); the diagonal columns are constants
        terms_i = [f"Di{x} * Ro{y}" for x, y in ((a, b), (b, a)) if c1[x] >= 0]
        terms_o = [f"Ri{y} * Do{x}" for x, y in ((b, a), (a, b)) if c1[x] >= 0]
        if not terms_i and q == 0:
            continue  # a constant output
        block = [f"{{ const T w = {_c(kc[k])} * g[{k}][j];"]
        if q >= 1:
            block += [f"  gG{q} += w * (Ri{a} * Ro{b} + Ri{b} * Ro{a});"]
        if terms_i:
            block += [f"  const T wg = w * G{q};",
                      f"  gzi += wg * ({' + '.join(terms_i)});",
                      f"  gzo += wg * ({' + '.join(terms_o)});"]
        block[-1] += " }"
        body += block
    ga1 = " + ".join(f"gG{q} * Ga{q}" for q in range(1, P + 1)) or "(T)0"
    gr1 = " + ".join(f"gG{q} * Gr{q}" for q in range(2, P + 1)) or "(T)0"
    body += [f"const T ga1 = {ga1}, gr1 = {gr1};",
             f"(void)G{P};",
             "ISO_SMALL_CHAIN"]
    bwd += ["            " + ln for ln in body]
    bwd += ["        }",
            "    }",
            "    (void)bad;",
            "    return 0;",
            "}",
            ""]
    return "\n".join(fwd + bwd)


def source() -> str:
    """The text of ``kernels_iso_small.h``."""
    head = f'''/* GENERATED by tools/generate_iso_kernels.py (python tools/generate_iso_kernels.py): do not edit.
 *
 * The isotropic Helmholtz basis of two direction sets at orders {", ".join(map(str, ORDERS))} as straight-line code:
 * the general iso_dirs kernels of kernels_impl.h with the tables (torch_hsh.kernel._native_iso_spec)
 * written in as constants, one loop over the rows of a block doing all of a row in registers.
 * Included by kernels_impl.h (T, SUF, SQRT, TMAX, BS, IVDEP, store_rows, load_rows defined there).
 */

/* GCC vectorises these loops with 256-bit registers unless told otherwise; on a CPU with AVX-512 the
 * 512-bit ones make them about 15-20 % faster (the other kernels keep the compiler's choice). */
#if defined(__GNUC__) && !defined(__clang__) && defined(__AVX512F__)
#pragma GCC push_options
#pragma GCC target("prefer-vector-width=512")
#define ISO_SMALL_POP_OPTIONS
#endif

/* Geometry of row j shared by both passes (as geom_block): unit vectors, t = 2z - 1, a, rho, z clamped at 0
 * (zpi, zpo) and the flag v. */
#define ISO_SMALL_UNIT                                                                                   \\
    T xi = wib[3 * j], yi = wib[3 * j + 1], zi = wib[3 * j + 2];                                           \\
    T xo = wob[3 * j], yo = wob[3 * j + 1], zo = wob[3 * j + 2];                                           \\
    const T ni = xi * xi + yi * yi + zi * zi, no = xo * xo + yo * yo + zo * zo;                           \\
    bad |= !(ni <= TMAX) | !(no <= TMAX);                                                                \\
    const int oki = ni > tiny, oko = no > tiny;                                                          \\
    const T ii = oki ? (T)1 / SQRT(ni) : (T)1, io = oko ? (T)1 / SQRT(no) : (T)1;                        \\
    xi *= ii; yi *= ii; zi *= ii;                                                                        \\
    xo *= io; yo *= io; zo *= io;                                                                        \\
    const T zpi = zi > 0 ? zi : (T)0, zpo = zo > 0 ? zo : (T)0;                                          \\
    const T ti = 2 * zi - 1, to = 2 * zo - 1;                                                            \\
    const T a = xi * xo + yi * yo, rho = (xi * xi + yi * yi) * (xo * xo + yo * yo);                      \\
    const T v = (oki && oko && zi >= 0 && zo >= 0) ? (T)1 : (T)0;

/* The backward's geometry: ISO_SMALL_UNIT, s_i, s_o (their derivatives need them apart) and sio = s_i s_o. */
#define ISO_SMALL_GEOM                                                                                   \\
    ISO_SMALL_UNIT                                                                                       \\
    const T si = SQRT(zpi / (1 + zpi)), so = SQRT(zpo / (1 + zpo)), sio = si * so;

/* The forward's geometry: ISO_SMALL_UNIT and only the product sio = s_i s_o, whose square
 * sio2 = z_i z_o / ((1 + z_i)(1 + z_o)) takes one square root and one division instead of two of each. */
#define ISO_SMALL_GEOM_FWD                                                                               \\
    ISO_SMALL_UNIT                                                                                       \\
    const T sio2 = zpi * zpo / ((1 + zpi) * (1 + zpo)), sio = SQRT(sio2);

/* The backward's extra geometry: ds/dz of both directions (horizon-safe, cut to zero for z <= eps). */
#define ISO_SMALL_GEOM_BWD                                                                               \\
    const T dsi = zpi > eps ? (T)0.5 / (si * (1 + zpi) * (1 + zpi)) : (T)0;                              \\
    const T dso = zpo > eps ? (T)0.5 / (so * (1 + zpo) * (1 + zpo)) : (T)0;

/* From ga1, gr1, gzi, gzo (gradients with respect to a1 = sio a, r1 = sio^2 rho, z_i, z_o) to the
 * gradients of the two (unnormalised) directions (as iso_dirs_bwd). */
#define ISO_SMALL_CHAIN                                                                                  \\
    {{                                                                                                    \\
        const T gA = ga1 * sio, gR = gr1 * sio * sio, gS = ga1 * a + gr1 * 2 * sio * rho;                \\
        const T pi = xi * xi + yi * yi, po = xo * xo + yo * yo;                                          \\
        const T gxi = gA * xo + gR * 2 * xi * po, gyi = gA * yo + gR * 2 * yi * po;                      \\
        const T gzi_ = gzi + gS * so * dsi;                                                              \\
        const T gxo = gA * xi + gR * 2 * xo * pi, gyo = gA * yi + gR * 2 * yo * pi;                      \\
        const T gzo_ = gzo + gS * si * dso;                                                              \\
        const T pdi = xi * gxi + yi * gyi + zi * gzi_, pdo = xo * gxo + yo * gyo + zo * gzo_;            \\
        T *gi = gwi + 3 * (b0 + j), *go = gwo + 3 * (b0 + j);                                            \\
        gi[0] = ii * (gxi - xi * pdi); gi[1] = ii * (gyi - yi * pdi); gi[2] = ii * (gzi_ - zi * pdi);    \\
        go[0] = io * (gxo - xo * pdo); go[1] = io * (gyo - yo * pdo); go[2] = io * (gzo_ - zo * pdo);    \\
    }}

'''
    parts = [head] + [_order_source(P) for P in ORDERS]
    cases_f = "\n".join(f"    case {P}: return SUF(iso{P}_fwd)(r0, r1, wi, wo, tiny, out);" for P in ORDERS)
    cases_b = "\n".join(f"    case {P}: return SUF(iso{P}_bwd)(r0, r1, wi, wo, tiny, eps, gout, gs0, gs1, gwi, gwo);"
                        for P in ORDERS)
    parts.append(f'''/* Dispatch on the order (-1: no generated kernel for it; the caller uses iso_dirs). */
int SUF(iso_small_fwd)(int64_t r0, int64_t r1, int P, const T *wi, const T *wo, T tiny, T eps, T *out)
{{
    (void)eps;
    switch (P) {{
{cases_f}
    default: return -1;
    }}
}}

int SUF(iso_small_bwd)(int64_t r0, int64_t r1, int P, const T *wi, const T *wo, T tiny, T eps, const T *gout,
                       int64_t gs0, int64_t gs1, T *gwi, T *gwo)
{{
    switch (P) {{
{cases_b}
    default: return -1;
    }}
}}

#ifdef ISO_SMALL_POP_OPTIONS
#pragma GCC pop_options
#undef ISO_SMALL_POP_OPTIONS
#endif
#undef ISO_SMALL_UNIT
#undef ISO_SMALL_GEOM
#undef ISO_SMALL_GEOM_FWD
#undef ISO_SMALL_GEOM_BWD
#undef ISO_SMALL_CHAIN
''')
    return "\n".join(parts)


def main(argv: List[str]) -> int:
    text = source()
    if argv[1:] == ["--check"]:
        ok = TARGET.exists() and TARGET.read_text() == text
        print(f"{TARGET.name}: {'up to date' if ok else 'STALE: run python tools/generate_iso_kernels.py'}")
        return 0 if ok else 1
    TARGET.write_text(text)
    print(f"wrote {TARGET}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
