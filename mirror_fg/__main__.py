"""``python -m mirror_fg``: the ``mirror-fg`` command line."""
import sys

from mirror_fg.cli import main

sys.exit(main())
