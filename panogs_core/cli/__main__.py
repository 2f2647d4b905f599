"""``python -m panogs_core.cli``: the ``panogs`` command without its console script."""

import sys

from panogs_core.cli.main import main

sys.exit(main())
