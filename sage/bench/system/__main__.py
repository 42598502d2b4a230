"""``python -m sage.bench.system {local-actor|echo}``: the bench's child processes."""
import sys

from sage.bench.system.children import main

sys.exit(main())
