"""``python -m panogs_core.cli``: the ``panogs`` command without its console script."""

import sys

from panogs_core.cli.main import main

if __name__ == "__main__":  # importing the module (a scan of the package) runs nothing
    sys.exit(main())
