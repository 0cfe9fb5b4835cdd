"""Packaging for torch-hsh (import name ``torch_hsh``)."""
import re
from pathlib import Path

from setuptools import find_packages, setup

here = Path(__file__).parent
version = re.search(r'__version__ = "([^"]+)"', (here / "torch_hsh" / "__init__.py").read_text()).group(1)

setup(
    name="torch-hsh",
    version=version,
    description="Differentiable Helmholtz hemispherical-harmonic BRDF bases, fitting and photometric stereo for PyTorch",
    long_description=(here / "README.md").read_text(encoding="utf-8"),
    long_description_content_type="text/markdown",
    license="MIT",
    packages=find_packages(include=["torch_hsh", "torch_hsh.*"]),
    python_requires=">=3.9",
    # torch is deliberately a loose lower bound: install the CPU wheel first
    # (``pip install torch==2.13.0``) so that nothing pulls the CUDA build.
    install_requires=[
        "torch>=2.1",
        "numpy>=1.22",
        "scipy>=1.9",
        "kornia>=0.7",
        "OpenEXR>=3.2",
        "scikit-image>=0.21",
        "pyamg>=5.0",
        "threadpoolctl>=3.0",
    ],
    extras_require={
        "examples": ["matplotlib>=3.6", "tqdm>=4.60"],
        "test": ["pytest>=7", "hypothesis>=6", "matplotlib>=3.6", "tqdm>=4.60", "trimesh>=4.0"],
        "bench": ["e3nn>=0.5", "sphericart-torch>=0.5"],
        "mesh": ["trimesh>=4.0"],
    },
    classifiers=[
        "Programming Language :: Python :: 3",
        "Intended Audience :: Science/Research",
        "Topic :: Scientific/Engineering :: Image Processing",
    ],
)
