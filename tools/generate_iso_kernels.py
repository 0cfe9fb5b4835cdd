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
The orders are ``torch_hsh._native.ISO_SMALL_ORDERS``. The header says each thing once, as macros (the polar
columns of an order for both directions and both passes, its outputs as one table that both passes expand, one
frame for every kernel); preprocessed, it is the straight-line code.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import List

from torch_hsh._native import ISO_SMALL_ORDERS as ORDERS  # noqa: E402
from torch_hsh.kernel import _native_iso_spec  # noqa: E402

TARGET = Path(__file__).resolve().parent.parent / "torch_hsh" / "_native" / "kernels_iso_small.h"


def _hex(x: float) -> str:
    """An exact C literal of ``x``: a hexadecimal float, without the trailing zeros of its fraction."""
    mant, exp = float(x).hex().split("p")
    return f"{mant.rstrip('0').rstrip('.')}p{exp}"


def _c(x: float) -> str:
    """An exact C literal of ``x`` (hexadecimal float), cast to the kernel's type."""
    return f"(T){_hex(x)}"


def _macro(name: str, lines: List[str], doc: str = "") -> List[str]:
    """``#define name`` with ``lines`` as its body (continued with backslashes), under the comment ``doc`` (lines
    after the first start with `` * ``) where one is given."""
    body = [f"#define {name}"] + ["    " + ln for ln in lines]
    width = max(104, max(len(ln) for ln in body) + 1)
    return ([f"/* {doc} */"] if doc else []) + [ln.ljust(width) + "\\" for ln in body[:-1]] + [body[-1]]


def _frame_macros() -> List[str]:
    """``ISO_SMALL_FWD(P, K)`` and ``ISO_SMALL_BWD(P, K)``: the two kernels of order ``P`` with ``K`` outputs, from
    the macros of that order; they share the loops over the blocks of a row range and over the rows of a block
    (``ISO_SMALL_BLOCKS``, ``ISO_SMALL_ROWS``, each opening a brace that the kernel closes)."""
    blocks = ["for (int64_t b0 = r0; b0 < r1; b0 += BS) {",
              "    const int m = (int)((r1 - b0) < BS ? (r1 - b0) : BS);",
              "    const T *wib = wi + 3 * b0, *wob = wo + 3 * b0;"]
    row = ["static int SUF(iso##P##_fwd)(int64_t r0, int64_t r1, const T *wi, const T *wo, T tiny, T *out)",
           "{", "    T tmp[K][BS];", "    int bad = 0;", "    ISO_SMALL_BLOCKS", "        ISO_SMALL_ROWS"]
    fwd = row + ["            ISO_SMALL_GEOM_FWD",
                 "            const T a1 = sio * a, q1 = sio2 * rho;",
                 "            (void)q1;",
                 "            ISO##P##_POLAR(Ri, ti, Di, ISO_SMALL_DROP) ISO##P##_POLAR(Ro, to, Do, ISO_SMALL_DROP)",
                 "            ISO_SMALL_AZIM##P(ISO_SMALL_DROP)",
                 "            ISO##P##_OUTPUTS(ISO_SMALL_OUT)",
                 "        }",
                 "        SUF(store_rows)(m, K, tmp, out + b0 * K);",
                 "    }",
                 "    return bad ? 2 : 0;",
                 "}"]
    bwd = ["static int SUF(iso##P##_bwd)(int64_t r0, int64_t r1, const T *wi, const T *wo, T tiny, T eps,",
           "                             const T *gout, int64_t gs0, int64_t gs1, T *gwi, T *gwo)",
           "{",
           "    T g[K][BS];",
           "    int bad = 0; /* set by ISO_SMALL_GEOM; the forward reports non-finite input */",
           "    ISO_SMALL_BLOCKS",
           "        SUF(load_rows)(m, K, gout + b0 * gs0, gs0, gs1, g);",
           "        ISO_SMALL_ROWS",
           "            ISO_SMALL_GEOM",
           "            ISO_SMALL_GEOM_BWD",
           "            const T a1 = sio * a, q1 = sio * sio * rho;",
           "            (void)q1;",
           "            ISO##P##_POLAR(Ri, ti, Di, ISO_SMALL_KEEP) ISO##P##_POLAR(Ro, to, Do, ISO_SMALL_KEEP)",
           "            ISO_SMALL_AZIM##P(ISO_SMALL_KEEP)",
           "            ISO##P##_GG_ZERO",
           "            T gzi = 0, gzo = 0;",
           "            ISO##P##_OUTPUTS(ISO_SMALL_GRAD)",
           "            ISO##P##_GG_CHAIN",
           "            ISO_SMALL_CHAIN",
           "        }",
           "    }",
           "    (void)bad;",
           "    return 0;",
           "}"]
    return ["/* The parts of a row that only the backward needs stand in DZ(...) or DG(...): the backward passes",
            " * ISO_SMALL_KEEP, the forward ISO_SMALL_DROP. */",
            "#define ISO_SMALL_KEEP(x) x", "#define ISO_SMALL_DROP(x)", ""] + _macro(
        "ISO_SMALL_BLOCKS", blocks, "The loop over the blocks of BS rows in [r0, r1) (wib, wob: the block's "
        "directions), left open.") + [""] + _macro(
        "ISO_SMALL_ROWS", ["IVDEP", "for (int j = 0; j < m; ++j) {"], "The loop over the m rows j of a block, left "
        "open.") + [""] + _macro(
        "ISO_SMALL_FWD(P, K)", fwd, "The forward of order P with K outputs: output k of row j goes to tmp[k][j], "
        "then a block at\n * a time to out.") + [""] + _macro(
        "ISO_SMALL_BWD(P, K)", bwd, "The backward of order P with K outputs: a row's gradients of G (gG1 .. gGP), "
        "z_i and z_o\n * (gzi, gzo), then of a1 and q1 (ga1, gr1), through ISO_SMALL_CHAIN to those of the two "
        "directions.") + [""]


def _output_macros() -> List[str]:
    """The ``X`` of the tables ``ISO<P>_OUTPUTS(X)``: an output in the forward (``ISO_SMALL_OUT``) and its terms of
    the backward (``ISO_SMALL_GRAD``, one macro a ``kind``)."""
    z1 = ["const T wg = w * G##q;", "gzi += wg * (Di##a * Ro##b);", "gzo += wg * (Ri##b * Do##a);"]
    z2 = ["const T wg = w * G##q;", "gzi += wg * (Di##a * Ro##b + Di##b * Ro##a);",
          "gzo += wg * (Ri##a * Do##b + Ri##b * Do##a);"]
    kinds = {"C": "", "G": "ISO_SMALL_GG(a, b, q)", "Z1": "ISO_SMALL_Z1(a, b, q)", "Z2": "ISO_SMALL_Z2(a, b, q)",
             "GZ1": "ISO_SMALL_GG(a, b, q) ISO_SMALL_Z1(a, b, q)", "GZ2": "ISO_SMALL_GG(a, b, q) ISO_SMALL_Z2(a, b, q)"}
    out = ["/* Output k of a row is c (Ri_a Ro_b + Ri_b Ro_a) G_q (ISO_SMALL_SYM: the bracket); the tables",
           " * ISO<P>_OUTPUTS hold X(k, c, a, b, q, kind) for each. The forward stores it (ISO_SMALL_OUT); the",
           " * backward (ISO_SMALL_GRAD) adds, with w = c g[k][j], its terms to the gradient gG##q of G_q (kinds G,",
           " * GZ1, GZ2: q >= 1) and to those of z_i and z_o, gzi and gzo, through column a alone (Z1, GZ1) or both",
           " * columns (Z2, GZ2): the column of the lowest degree, q, is a constant. Kind C, a constant, has none. */",
           "#define ISO_SMALL_SYM(a, b) (Ri##a * Ro##b + Ri##b * Ro##a)",
           "#define ISO_SMALL_OUT(k, c, a, b, q, kind) tmp[k][j] = (T)c * ISO_SMALL_SYM(a, b) * G##q;",
           "#define ISO_SMALL_GRAD(k, c, a, b, q, kind) ISO_SMALL_GRAD_##kind(k, c, a, b, q)",
           "#define ISO_SMALL_W(k, c) const T w = (T)c * g[k][j];",
           "#define ISO_SMALL_GG(a, b, q) gG##q += w * ISO_SMALL_SYM(a, b);"]
    out += _macro("ISO_SMALL_Z1(a, b, q)", z1) + _macro("ISO_SMALL_Z2(a, b, q)", z2)
    for kind, body in kinds.items():
        out.append(f"#define ISO_SMALL_GRAD_{kind}(k, c, a, b, q)" + (body and f" {{ ISO_SMALL_W(k, c) {body} }}"))
    return out + [""]


def _azimuthal_macros(top: int) -> List[str]:
    """``ISO_SMALL_AZIM<q>(DG)`` for q = 1 .. ``top``: the azimuthal factors ``G0 .. G<q>`` of a row (Chebyshev
    recurrence in a1, q1), each from the one of q - 1, and in ``DG(...)`` their derivatives with respect to a1
    (``Ga``) and q1 (``Gr``)."""
    out = ["/* The azimuthal factors G0 .. Gq of a row, by their recurrence in a1 and q1, and in DG(...) dG/da1 (Ga)",
           " * and dG/dq1 (Gr). */",
           "#define ISO_SMALL_AZIM1(DG) const T G0 = v; const T G1 = a1 * v; DG(const T Ga1 = v;)"]
    for q in range(2, top + 1):
        ga_prev2 = f" - q1 * Ga{q - 2}" if q - 2 >= 1 else ""
        gr = (f"2 * a1 * Gr{q - 1} - " if q - 1 >= 2 else "-") + f"G{q - 2}"
        gr += f" - q1 * Gr{q - 2}" if q - 2 >= 2 else ""
        out += _macro(f"ISO_SMALL_AZIM{q}(DG)", [
            f"ISO_SMALL_AZIM{q - 1}(DG)", f"const T G{q} = 2 * a1 * G{q - 1} - q1 * G{q - 2};",
            f"DG(const T Ga{q} = 2 * G{q - 1} + 2 * a1 * Ga{q - 1}{ga_prev2}; const T Gr{q} = {gr};)"])
    return out + [""]


def _polar_macro(P: int, L: int, A, B, c1, c2) -> List[str]:
    """``ISO<P>_POLAR(R, t, D, DZ)``: the polar columns ``R##0 .. R##<L-1>`` of one direction from its
    ``t = 2z - 1`` (the constant ones two to a line) and after each other one ``DZ(...)`` of its derivative ``D##c``
    with respect to z."""
    consts = [f"R##{c} = {_c(A[c])}" for c in range(L) if c1[c] < 0]
    lines = ["const T " + ", ".join(consts[i:i + 2]) + ";" for i in range(0, len(consts), 2)]
    for c in range(L):
        if c1[c] < 0:
            continue
        expr = f"{_c(A[c])} * t * R##{c1[c]}" + (f" - {_c(B[c])} * R##{c2[c]}" if c2[c] >= 0 else "")
        # d/dz of A t R1 - B R2 with t = 2z - 1 (the derivative of a constant column is 0 and left out)
        dexpr = f"{_c(A[c])} * (2 * R##{c1[c]}" + (f" + t * D##{c1[c]})" if c1[c1[c]] >= 0 else ")")
        if c2[c] >= 0 and c1[c2[c]] >= 0:
            dexpr += f" - {_c(B[c])} * D##{c2[c]}"
        lines += [f"const T R##{c} = {expr};", f"DZ(const T D##{c} = {dexpr};)"]
    doc = (f"P = {P}: the {L} polar columns R##0 .. R##{L - 1} of one direction (R, t, D: Ri, ti, Di or Ro, to, Do)"
           "\n * and in DZ(...) the derivatives D##c of the non-constant ones with respect to z.")
    return _macro(f"ISO{P}_POLAR(R, t, D, DZ)", lines, doc) + [""]


def _gradient_macros(P: int) -> List[str]:
    """``ISO<P>_GG_ZERO``: the gradients ``gG`` of ``G1 .. G<P>``, zeroed (the outputs add to them), and
    ``ISO<P>_GG_CHAIN``: from them those of a1 and q1, ``ga1`` and ``gr1``."""
    ga1 = " + ".join(f"gG{q} * Ga{q}" for q in range(1, P + 1))
    gr1 = " + ".join(f"gG{q} * Gr{q}" for q in range(2, P + 1)) or "(T)0"
    return [f"/* P = {P}: the gradients gG of the azimuthal factors, zeroed, and from them those of a1 and q1. */",
            f"#define ISO{P}_GG_ZERO " + " ".join(f"T gG{q} = 0;" for q in range(1, P + 1)),
            f"#define ISO{P}_GG_CHAIN const T ga1 = {ga1}, gr1 = {gr1}; (void)G{P};", ""]


def _outputs_macro(P: int, c1, ka, kb, kq, kc) -> List[str]:
    """``ISO<P>_OUTPUTS(X)``: ``X(k, c, a, b, q, kind)`` for every output, ``P`` to a line (see ``_output_macros``);
    the forward and the backward expand the one table."""
    entries = []
    for k, (a, b, q) in enumerate(zip(ka, kb, kq)):
        if c1[b] >= 0 > c1[a]:
            raise ValueError(f"P = {P}, output {k}: column {b} varies with z but column {a} does not")
        z = "Z2" if c1[b] >= 0 else "Z1" if c1[a] >= 0 else ""
        kind = ("G" if q >= 1 else "") + z or "C"
        entries.append(f"X({k}, {_hex(kc[k])}, {a}, {b}, {q}, {kind})")
    lines = [" ".join(entries[i:i + P]) for i in range(0, len(entries), P)]
    return _macro(f"ISO{P}_OUTPUTS(X)", lines, f"P = {P}: the {len(entries)} outputs, X(k, c, a, b, q, kind) each.")


def _order_source(P: int) -> str:
    """The macros of order ``P`` (the kernels expand them: ISO_SMALL_FWD, ISO_SMALL_BWD)."""
    L, A, B, c1, c2, ka, kb, kq, kc = _native_iso_spec(P)
    lines = [f"/* ---- P = {P}: L = {L} polar columns, K = {len(ka)} outputs ---- */"]
    lines += _polar_macro(P, L, A, B, c1, c2) + _gradient_macros(P) + _outputs_macro(P, c1, ka, kb, kq, kc)
    return "\n".join(lines) + "\n"


def source() -> str:
    """The text of ``kernels_iso_small.h``."""
    head = f'''/* GENERATED by tools/generate_iso_kernels.py (python tools/generate_iso_kernels.py): do not edit.
 *
 * The isotropic Helmholtz basis of two direction sets at orders {", ".join(map(str, ORDERS))} as straight-line code:
 * the general iso_dirs kernels of kernels_impl.h with the tables (torch_hsh.kernel._native_iso_spec)
 * written in as constants, one loop over the rows of a block doing all of a row in registers.
 * An order P is a few macros: its polar columns (ISO<P>_POLAR, for either direction), the gradients of its
 * azimuthal factors (ISO<P>_GG_*) and its table of outputs (ISO<P>_OUTPUTS); its kernels iso<P>_fwd and
 * iso<P>_bwd are ISO_SMALL_FWD(P, K) and ISO_SMALL_BWD(P, K) of them, the backward keeping what the forward drops.
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
    parts = [head + "\n".join(_frame_macros() + _output_macros() + _azimuthal_macros(max(ORDERS)))]
    parts += [_order_source(P) for P in ORDERS]
    sizes = [(P, len(_native_iso_spec(P)[5])) for P in ORDERS]
    parts.append("/* The kernels iso<P>_fwd and iso<P>_bwd of every order. */\n"
                 + "\n".join(f"ISO_SMALL_FWD({P}, {K}) ISO_SMALL_BWD({P}, {K})" for P, K in sizes) + "\n")
    cases_f = "\n".join(f"    case {P}: return SUF(iso{P}_fwd)(r0, r1, wi, wo, tiny, out);" for P in ORDERS)
    cases_b = "\n".join(f"    case {P}: return SUF(iso{P}_bwd)(r0, r1, wi, wo, tiny, eps, gout, gs0, gs1, gwi, gwo);"
                        for P in ORDERS)
    names = re.findall(r"^#define (ISO\w+)", "\n".join(parts), re.M)
    undefs = "\n".join(f"#undef {n}" for n in names if n != "ISO_SMALL_POP_OPTIONS")
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
{undefs}
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
