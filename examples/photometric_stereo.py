"""Photometric stereo with the isotropic Helmholtz HSH basis: the demo behind ``make demo``.

A thin wrapper around the installed commands: without a capture it runs ``torch-hsh demo`` (a
synthetic 128x128 bumpy sphere with GGX and Blinn-Phong regions over a textured albedo, 96
DiLiGenT-like lights with RGB intensities, cast shadows, sensor noise, 16-bit quantisation), solves it
with Lambertian least squares, robust (trimmed) Lambertian and the HSH solver, prints a table and
writes ``results/ps_demo``. With a capture folder as the first argument it runs ``torch-hsh ps CAPTURE``
instead. Every other argument is passed on (see ``torch-hsh demo --help`` and ``torch-hsh ps --help``).

Example:
    python examples/photometric_stereo.py                       # the demo scene -> results/ps_demo
    python examples/photometric_stereo.py --scene small         # the quick one
    python examples/photometric_stereo.py ../shared/data/bunny_specular --holdout 5 --out results/bunny
"""
import sys

from torch_hsh.cli import run


def main(argv=None):
    """Run ``torch-hsh demo`` (or ``torch-hsh ps CAPTURE``) with ``argv``; returns the metrics dict."""
    argv = list(sys.argv[1:] if argv is None else argv)
    command = ["ps"] if argv and not argv[0].startswith("-") else ["demo"]
    if not any(a == "--out" or a.startswith("--out=") for a in argv) and "-h" not in argv and "--help" not in argv:
        argv += ["--out", "results/ps_demo" if command == ["demo"] else f"results/{_name(argv[0])}_ps"]
    return run(command + argv)


def _name(capture: str) -> str:
    from pathlib import Path

    p = Path(capture).resolve()
    return p.stem if p.suffix.lower() == ".lp" else p.name


if __name__ == "__main__":
    main()
    sys.exit(0)
