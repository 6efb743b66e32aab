"""``python -m tuning``: the ``jaxcart`` command line."""

import sys

from tuning.cli import main

sys.exit(main())
