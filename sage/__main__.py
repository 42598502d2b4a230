"""python -m sage ... (the same as the ``sage`` console script)."""
import sys

from sage.cli import main

if __name__ == "__main__":
    sys.exit(main())
