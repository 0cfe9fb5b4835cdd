"""``python -m torch_hsh``: the ``torch-hsh`` command (see :mod:`torch_hsh.cli`)."""
import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
