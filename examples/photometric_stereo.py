"""Photometric stereo with the isotropic Helmholtz HSH basis: demo and driver.

A thin wrapper around the installed command ``torch-hsh ps`` (see
:mod:`torch_hsh.cli` for every option and the output-folder contract); ``make
demo`` runs it. Without arguments it renders a synthetic non-Lambertian scene
(a sphere with GGX, Blinn-Phong and Torrance-Sparrow regions over a textured
albedo, DiLiGenT-like lights with RGB intensities, sensor noise, 16-bit
quantisation), solves it with Lambertian least squares, robust (trimmed)
Lambertian and the HSH solver, prints a table and writes ``results/ps_demo``.
With ``--data DIR`` it solves a DiLiGenT-layout folder instead.

Example:
    python examples/photometric_stereo.py --out results/ps_demo
    python examples/photometric_stereo.py --data ../shared/data/bunny_specular --holdout 5
"""
import sys

from torch_hsh.cli import ps_main, synthetic_scene  # noqa: F401  (synthetic_scene: used by benchmarks)


def main(argv=None):
    """Run ``torch-hsh ps`` with ``argv``; returns the metrics dict."""
    return ps_main(argv)


if __name__ == "__main__":
    main()
    sys.exit(0)
