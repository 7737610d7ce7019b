"""``python -m mirror_fg.cli``: the ``mirror-fg`` command."""
import sys

from mirror_fg.cli import main

sys.exit(main())
